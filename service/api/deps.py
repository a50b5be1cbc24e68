"""What routes are given rather than fetch: settings, the store's repositories, benches, the job
manager, the streams and the webhook dispatcher, each as an `Annotated[..., Depends(...)]` type. The
application's lifespan puts them on `app.state`; only this module reads it (routes, tests and other
apps stay decoupled from where they live). The caller (token and scope) comes from service.api.auth:
Reader, Operator, Admin. Each is an `async def`: FastAPI runs a plain `def` dependency in its thread
pool, a thread hop per dependency per request for what is an attribute read."""

from __future__ import annotations

from typing import Annotated, cast

import sqlalchemy as sa
from fastapi import Depends, Path, Query
from starlette.requests import HTTPConnection

from service.api.auth import TokenCache, TokenChecks
from service.api.problems import ProblemError
from service.api.revision import SchemaRevision
from service.bench.runtime import BenchRuntime
from service.config import Settings
from service.fleet import Fleet
from service.jobs.diagnosis import DiagnosisRunner
from service.jobs.manager import JobManager
from service.jobs.requests import DB_ID_MAX
from service.lims.webhooks import Dispatcher
from service.storage.disk import DiskWatch
from service.storage.engine import redacted
from service.storage.outage import DatabaseState
from service.storage.store import (
    ApprovalsRepo,
    AuditRepo,
    CertificatesRepo,
    DevicesRepo,
    DiagnosesRepo,
    FeedRepo,
    JobsRepo,
    OrdersRepo,
    PointsRepo,
    RecordsRepo,
    StandardsRepo,
    Store,
    TokensRepo,
    WebhooksRepo,
)
from service.streams.readings import StreamHub


async def get_settings(conn: HTTPConnection) -> Settings:
    return cast(Settings, conn.app.state.settings)


async def get_engine(conn: HTTPConnection) -> sa.Engine:
    return cast(sa.Engine, conn.app.state.engine)


async def get_store(conn: HTTPConnection) -> Store:
    return cast(Store, conn.app.state.store)


async def get_benches(conn: HTTPConnection) -> dict[str, BenchRuntime]:
    return cast(dict[str, BenchRuntime], conn.app.state.benches)


async def get_jobs(conn: HTTPConnection) -> JobManager:
    return cast(JobManager, conn.app.state.jobs)


async def get_jobs_if_any(conn: HTTPConnection) -> JobManager | None:
    """The job manager, None in an application that runs no benches (the LIMS routes alone)."""
    return cast(JobManager | None, getattr(conn.app.state, "jobs", None))


async def get_streams(conn: HTTPConnection) -> StreamHub:
    return cast(StreamHub, conn.app.state.streams)


async def get_schema_revision(conn: HTTPConnection) -> SchemaRevision:
    """The application's one SchemaRevision (made on first use where the lifespan made none)."""
    rev = getattr(conn.app.state, "schema_revision", None)
    if not isinstance(rev, SchemaRevision):
        rev = conn.app.state.schema_revision = SchemaRevision()
    return rev


async def get_database(conn: HTTPConnection) -> DatabaseState:
    """Whether the database answers, as the daemon last found it (one per application)."""
    state = getattr(conn.app.state, "database", None)
    if not isinstance(state, DatabaseState):
        state = conn.app.state.database = DatabaseState(
            redacted(cast(sa.Engine, conn.app.state.engine).url)
        )
    return state


async def get_fleet(conn: HTTPConnection) -> Fleet | None:
    """This daemon's membership of the fleet; None when it runs alone."""
    return cast(Fleet | None, getattr(conn.app.state, "fleet", None))


async def get_token_cache(conn: HTTPConnection) -> TokenCache | None:
    """The cache of recently seen tokens, cleared when one is revoked."""
    checks = getattr(conn.app.state, "token_checks", None)
    return checks.cache if isinstance(checks, TokenChecks) else None


async def get_disk(conn: HTTPConnection) -> DiskWatch | None:
    """The free space of the folders the daemon writes, against the least it keeps; None without a
    lifespan."""
    return cast(DiskWatch | None, getattr(conn.app.state, "disk", None))


async def get_diagnoses(conn: HTTPConnection) -> DiagnosisRunner:
    return cast(DiagnosisRunner, conn.app.state.diagnoses)


async def get_webhooks(conn: HTTPConnection) -> Dispatcher | None:
    """The webhook dispatcher, None where the application runs none."""
    return cast(Dispatcher | None, getattr(conn.app.state, "webhooks", None))


SettingsDep = Annotated[Settings, Depends(get_settings)]
EngineDep = Annotated[sa.Engine, Depends(get_engine)]
StoreDep = Annotated[Store, Depends(get_store)]


# One repository per aggregate, for a route that needs that one.
async def get_devices_repo(store: StoreDep) -> DevicesRepo:
    return store.devices


async def get_jobs_repo(store: StoreDep) -> JobsRepo:
    return store.jobs


async def get_points_repo(store: StoreDep) -> PointsRepo:
    return store.points


async def get_records_repo(store: StoreDep) -> RecordsRepo:
    return store.records


async def get_audit_repo(store: StoreDep) -> AuditRepo:
    return store.audit


async def get_tokens_repo(store: StoreDep) -> TokensRepo:
    return store.tokens


async def get_diagnoses_repo(store: StoreDep) -> DiagnosesRepo:
    return store.diagnoses


async def get_standards_repo(store: StoreDep) -> StandardsRepo:
    return store.standards


async def get_approvals_repo(store: StoreDep) -> ApprovalsRepo:
    return store.approvals


async def get_certificates_repo(store: StoreDep) -> CertificatesRepo:
    return store.certificates


async def get_orders_repo(store: StoreDep) -> OrdersRepo:
    return store.orders


async def get_feed_repo(store: StoreDep) -> FeedRepo:
    return store.feed


async def get_webhooks_repo(store: StoreDep) -> WebhooksRepo:
    return store.webhooks


DevicesRepoDep = Annotated[DevicesRepo, Depends(get_devices_repo)]
JobsRepoDep = Annotated[JobsRepo, Depends(get_jobs_repo)]
PointsRepoDep = Annotated[PointsRepo, Depends(get_points_repo)]
RecordsRepoDep = Annotated[RecordsRepo, Depends(get_records_repo)]
AuditRepoDep = Annotated[AuditRepo, Depends(get_audit_repo)]
TokensRepoDep = Annotated[TokensRepo, Depends(get_tokens_repo)]
DiagnosesRepoDep = Annotated[DiagnosesRepo, Depends(get_diagnoses_repo)]
StandardsRepoDep = Annotated[StandardsRepo, Depends(get_standards_repo)]
ApprovalsRepoDep = Annotated[ApprovalsRepo, Depends(get_approvals_repo)]
CertificatesRepoDep = Annotated[CertificatesRepo, Depends(get_certificates_repo)]
OrdersRepoDep = Annotated[OrdersRepo, Depends(get_orders_repo)]
FeedRepoDep = Annotated[FeedRepo, Depends(get_feed_repo)]
WebhooksRepoDep = Annotated[WebhooksRepo, Depends(get_webhooks_repo)]
BenchesDep = Annotated[dict[str, BenchRuntime], Depends(get_benches)]
JobsDep = Annotated[JobManager, Depends(get_jobs)]
JobsIfAnyDep = Annotated[JobManager | None, Depends(get_jobs_if_any)]
StreamsDep = Annotated[StreamHub, Depends(get_streams)]
RevisionDep = Annotated[SchemaRevision, Depends(get_schema_revision)]
DatabaseDep = Annotated[DatabaseState, Depends(get_database)]
FleetDep = Annotated[Fleet | None, Depends(get_fleet)]
TokenCacheDep = Annotated[TokenCache | None, Depends(get_token_cache)]
DiagnosesDep = Annotated[DiagnosisRunner, Depends(get_diagnoses)]
DiskDep = Annotated[DiskWatch | None, Depends(get_disk)]
WebhooksDep = Annotated[Dispatcher | None, Depends(get_webhooks)]


def find_bench(
    benches: dict[str, BenchRuntime], name: str | None, field: str = "bench"
) -> BenchRuntime:
    """The named bench, or the only one when the daemon runs one and no name is given."""
    if name is None:
        if len(benches) == 1:
            return next(iter(benches.values()))
        raise ProblemError(
            422,
            "Bench not named",
            f"{field}: the daemon runs {len(benches)} benches ({', '.join(benches)}); name one",
            field=field,
        )
    if name not in benches:
        raise ProblemError(
            404,
            "Unknown bench",
            f"{field}: no bench named {name[:100]!r}; benches: {', '.join(benches)}",
            field=field,
        )
    return benches[name]


async def bench_from_query(
    benches: BenchesDep,
    bench: Annotated[
        str | None,
        Query(
            max_length=100,
            description="bench name; may be left out when the daemon runs a single bench",
        ),
    ] = None,
) -> BenchRuntime:
    return find_bench(benches, bench)


BenchQuery = Annotated[BenchRuntime, Depends(bench_from_query)]


# Ids in paths: one the database cannot hold names nothing (404), rather than reaching the database.
def _known_range(value: int, what: str) -> int:
    if not 1 <= value <= DB_ID_MAX:
        raise ProblemError(404, "Not found", f"id: no {what} {value}", field="id")
    return value


async def _job_id(job_id: Annotated[int, Path(description="the job's id")]) -> int:
    return _known_range(job_id, "calibration job")


async def _record_id(record_id: Annotated[int, Path(description="the record's id")]) -> int:
    return _known_range(record_id, "calibration record")


async def _standard_id(
    standard_id: Annotated[int, Path(description="the reference standard's id")],
) -> int:
    return _known_range(standard_id, "reference standard")


async def _order_id(order_id: Annotated[int, Path(description="the order's id")]) -> int:
    return _known_range(order_id, "order")


async def _diagnosis_id(
    diagnosis_id: Annotated[int, Path(description="the diagnosis's id")],
) -> int:
    return _known_range(diagnosis_id, "diagnosis")


async def _webhook_id(webhook_id: Annotated[int, Path(description="the webhook's id")]) -> int:
    return _known_range(webhook_id, "webhook")


JobId = Annotated[int, Depends(_job_id)]
RecordId = Annotated[int, Depends(_record_id)]
StandardId = Annotated[int, Depends(_standard_id)]
OrderId = Annotated[int, Depends(_order_id)]
DiagnosisId = Annotated[int, Depends(_diagnosis_id)]
WebhookId = Annotated[int, Depends(_webhook_id)]
