from __future__ import annotations

from fastapi import APIRouter

from service import __version__
from service.api.deps import BenchDep, EngineDep
from service.storage.engine import redacted
from service.storage.migrate import current_revision, head_revision

router = APIRouter(tags=["health"])


@router.get("/health")
def health(engine: EngineDep, bench: BenchDep) -> dict:
    """Liveness plus what the service runs on: version, database and schema revision, bench."""
    rev = current_revision(engine)
    return {"status": "ok" if rev == head_revision() else "degraded", "version": __version__,
            "database": redacted(engine.url), "schema_revision": rev, "bench": bench.name}
