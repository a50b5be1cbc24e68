from __future__ import annotations

from functools import cache

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from service import __version__
from service.api.deps import EngineDep
from service.storage.engine import redacted
from service.storage.migrate import current_revision, head_revision

router = APIRouter(tags=["health"])
_head = cache(head_revision)  # the migration scripts do not change while the daemon runs


@router.get("/health")
def health(engine: EngineDep, request: Request) -> dict:
    """Liveness plus what the service runs on: version, database and schema revision, benches. No token needed."""
    rev = current_revision(engine)
    benches = list(request.app.state.benches)
    return {"status": "ok" if rev == _head() else "degraded", "version": __version__,
            "database": redacted(engine.url), "schema_revision": rev,
            "bench": benches[0] if len(benches) == 1 else ", ".join(benches), "benches": benches}


@router.get("/ready")
def ready(engine: EngineDep, request: Request) -> JSONResponse:
    """Ready for work: the schema at head and every instrument of every bench connected (503 with the
    reasons otherwise). No token needed, like /health."""
    reasons = []
    rev = current_revision(engine)
    if rev != _head():
        reasons.append(f"database schema at {rev}, not {_head()}")
    for bench in request.app.state.benches.values():
        for st in bench.devices.status():
            if st.state != "connected":
                reasons.append(f"{bench.name}: {st.role} on {st.port} is {st.state}")
    body = {"ready": not reasons, "reasons": reasons}
    return JSONResponse(body, status_code=200 if not reasons else 503)
