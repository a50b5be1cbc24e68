"""/health and /ready: liveness and readiness, without a token."""

from __future__ import annotations

from functools import cache

from fastapi import APIRouter, Response

from service import __version__
from service.api.deps import BenchesDep, EngineDep, RevisionDep
from service.api.models.health import Health, Readiness
from service.api.revision import REVISION_TTL_S, SchemaRevision
from service.storage.engine import redacted
from service.storage.migrate import head_revision

__all__ = ["REVISION_TTL_S", "SchemaRevision", "router"]

router = APIRouter(tags=["health"])
_head = cache(head_revision)  # the migration scripts do not change while the daemon runs


@router.get("/health", response_model=Health)
async def health(engine: EngineDep, benches: BenchesDep, revision: RevisionDep) -> Health:
    """Liveness plus what the service runs on: version, database and schema revision (as read at most
    one second ago), benches. No token needed."""
    rev = await revision.get(engine)
    names = list(benches)
    return Health(status="ok" if rev == _head() else "degraded", version=__version__, database=redacted(engine.url),
                  schema_revision=rev, bench=names[0] if len(names) == 1 else ", ".join(names), benches=names)


@router.get("/ready", response_model=Readiness,
            responses={503: {"model": Readiness, "description": "Not ready: the reasons, one line each"}})
async def ready(engine: EngineDep, benches: BenchesDep, revision: RevisionDep, response: Response) -> Readiness:
    """Ready for work: the schema at head and every instrument of every bench connected (503 with the
    reasons otherwise). No token needed, like /health."""
    reasons = []
    rev = await revision.get(engine)
    if rev != _head():
        reasons.append(f"database schema at {rev}, not {_head()}")
    for bench in benches.values():
        for st in bench.devices.status():
            if st.state != "connected":
                reasons.append(f"{bench.name}: {st.role} on {st.port} is {st.state}")
    if reasons:
        response.status_code = 503
    return Readiness(ready=not reasons, reasons=reasons)
