"""/health and /ready: liveness and readiness, without a token."""

from __future__ import annotations

from functools import cache

from fastapi import APIRouter, Response

from service import __version__
from service.api.deps import BenchesDep, DatabaseDep, DiskDep, EngineDep, JobsIfAnyDep, RevisionDep
from service.api.models.health import DatabaseOutageState, DiskState, Health, Readiness
from service.api.revision import REVISION_TTL_S, SchemaRevision
from service.jobs.manager import JobManager
from service.storage.disk import DiskWatch
from service.storage.engine import redacted
from service.storage.migrate import head_revision
from service.storage.outage import DatabaseState

__all__ = ["REVISION_TTL_S", "SchemaRevision", "router"]

router = APIRouter(tags=["health"])
_head = cache(head_revision)  # the migration scripts do not change while the daemon runs


@router.get("/health", response_model=Health)
async def health(
    engine: EngineDep,
    benches: BenchesDep,
    revision: RevisionDep,
    database: DatabaseDep,
    jobs: JobsIfAnyDep,
    watch: DiskDep,
) -> Health:
    """Liveness plus what the service runs on: version, database (whether it answers) and schema
    revision (as read at most one second ago), benches. No token needed."""
    revision.database = database
    rev = await revision.get(engine)
    names = list(benches)
    outage = _outage_state(database, jobs)
    disks = _disk_states(watch)
    degraded = rev != _head() or outage is not None or any(space.full for space in disks)
    return Health(
        status="degraded" if degraded else "ok",
        version=__version__,
        database=redacted(engine.url),
        database_state="up" if outage is None else "away",
        database_outage=outage,
        schema_revision=rev,
        bench=names[0] if len(names) == 1 else ", ".join(names),
        benches=names,
        disk=disks,
        jobs_not_stored=sorted(jobs.unwritten) if jobs else [],
    )


def _outage_state(database: DatabaseState, jobs: JobManager | None) -> DatabaseOutageState | None:
    """The database's outage as /health shows it (since when, why, what waits); None while it is
    up."""
    if database.away_since_utc is None:
        return None
    return DatabaseOutageState(
        away_since_utc=database.away_since_utc,
        away_s=round(database.away_for_s(), 3),
        error=database.error,
        outage_limit_s=database.outage_s,
        jobs_waiting=sorted(jobs.waiting_for_database) if jobs else [],
        writes_waiting=database.writes_waiting,
        samples_waiting=database.samples_waiting,
    )


def _disk_states(watch: DiskWatch | None) -> list[DiskState]:
    """The free space of each folder the daemon writes, against the least it keeps."""
    if watch is None:
        return []
    return [
        DiskState(
            folder=str(space.folder),
            free_mb=round(space.free_mb, 3),
            min_free_mb=watch.min_free_mb,
            full=space.free_mb < watch.min_free_mb,
        )
        for space in watch.spaces()
    ]


@router.get(
    "/ready",
    response_model=Readiness,
    responses={503: {"model": Readiness, "description": "Not ready: the reasons, one line each"}},
)
async def ready(
    engine: EngineDep,
    benches: BenchesDep,
    revision: RevisionDep,
    database: DatabaseDep,
    watch: DiskDep,
    response: Response,
) -> Readiness:
    """Ready for work: the database answering with the schema at head, room on the disk and every
    instrument of every bench connected (503 with the reasons otherwise). No token needed, like
    /health."""
    reasons = []
    revision.database = database
    rev = await revision.get(engine)
    if not database.up:
        reasons.append(
            f"database {database.where} unreachable for {database.away_for_s():.0f} s: "
            f"{database.error}"
        )
    if rev != _head():
        reasons.append(f"database schema at {rev}, not {_head()}")
    short = watch.short() if watch is not None else None
    if short is not None:
        reasons.append(watch.reason(short))  # type: ignore[union-attr]
    for bench in benches.values():
        for st in bench.devices.status():
            if st.state != "connected":
                reasons.append(f"{bench.name}: {st.role} on {st.port} is {st.state}")
    if reasons:
        response.status_code = 503
    return Readiness(ready=not reasons, reasons=reasons)
