"""The tiltlab daemon: FastAPI application factory and its lifespan (database, tokens, benches,
jobs)."""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from functools import partial
from pathlib import Path

import sqlalchemy as sa
from fastapi import FastAPI, Request, Response
from fastapi_offline import FastAPIOffline

from service import __version__
from service.api import http_details, openapi, problems, redoc
from service.api.auth import Authentication, FailedTokens, TokenChecks, is_loopback
from service.api.csp import ContentSecurity
from service.api.fleet_routing import FleetRouting, run_forwarded
from service.api.limits import BodySizeLimit
from service.api.metrics import Metrics, MetricsMiddleware
from service.api.offloop import DatabaseCalls
from service.api.prepared_tilt import PreparedTilt
from service.api.redact import install_log_redaction
from service.api.revision import SchemaRevision
from service.api.routers import (
    benches,
    calibrations,
    dashboard,
    diagnoses,
    health,
    lims,
    records,
    stage,
    stage_home,
    streams,
    tilt,
    tokens,
)
from service.api.routers import metrics as metrics_router
from service.bench.runtime import (
    BenchBusy,
    BenchRuntime,
    DeviceNotAnswering,
    MotionStopped,
    StageNotHomed,
)
from service.bench.startup import check_sim_speed, plan_benches
from service.config import Settings, get_settings
from service.errors import InputError
from service.fleet import Fleet
from service.instruments.transport import DeviceError
from service.jobs.diagnosis import DiagnosesBusy, DiagnosisRunner
from service.jobs.manager import JobManager
from service.jobs.points import writes_in_flight
from service.jobs.requests import RequestProblem
from service.lims.runtime import LimsRuntime
from service.storage.disk import DiskFull, DiskWatch, disk_full, folders_of
from service.storage.engine import normalise_url, redacted
from service.storage.errors import ConflictError
from service.storage.migrate import bootstrap
from service.storage.outage import DatabaseOutage, DatabaseState, unreachable
from service.storage.store import Store
from service.storage.store.jobs import IdempotencyMismatch
from service.streams.readings import SnapshotGate, StreamHub

log = logging.getLogger("tiltlab")

# a diagnosis takes tens of seconds: when to ask again once they are all taken
DIAGNOSES_RETRY_AFTER_S = 30


def _check_benches(s: Settings) -> None:
    """Refuse an unusable scenario or bench configuration before anything is started."""
    if s.bench_config is not None:
        from service.instruments.bench_config import load_bench_config

        load_bench_config(s.bench_config)
        return
    from service.instruments.sim.world import rotary_scenarios, stage_scenario

    check_sim_speed(s)

    try:
        if "stage" in s.sim_benches:
            stage_scenario(s.bench_scenario)
    except InputError as exc:
        raise InputError(f"TILTLAB_BENCH_SCENARIO: {exc}") from exc
    try:
        if "rotary" in s.sim_benches:
            rotary_scenarios(s.rotary_scenario)
    except InputError as exc:
        raise InputError(f"TILTLAB_ROTARY_SCENARIO: {exc}") from exc


def write_admin_token(path: Path, token: str) -> Path:
    """The first admin token, readable by the daemon's user only (0600), written whole or not at
    all."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.write(fd, (token + "\n").encode())
            os.fsync(fd)
        finally:
            os.close(fd)
        os.chmod(tmp, 0o600)
        os.replace(tmp, path)
    except OSError as exc:
        raise InputError(
            f"TILTLAB_ADMIN_TOKEN_FILE: the first admin token cannot be written to {path} "
            f"({exc.strerror}); name a file in a folder this user can write (default: "
            "admin.token in TILTLAB_DATA_DIR)"
        ) from None
    return path


def announce_dashboard(store: Store, s: Settings, *, terminal: bool) -> None:
    """Make the lab's first admin token if the database has none, and say where the dashboard and
    its token are.

    The token's text goes only to an interactive terminal (`terminal`); a log, a journal or a
    container's output gets the dashboard's address and the token file. Of daemons starting together
    on a new database one makes the token; the others name the file it went to and the node that
    wrote it."""
    url = dashboard_url(s)
    if s.auth != "token":
        print(f"tiltlab: dashboard: {url} (authentication off)", file=sys.stderr, flush=True)
        return
    path = s.admin_token_path
    token = store.tokens.create_first_admin_token(
        node=s.node, file=str(path), write=partial(write_admin_token, path)
    )
    if token is not None:
        shown = f"{url}#token={token}" if terminal else f"{url} (token: the admin token in {path})"
        print(
            f"tiltlab: first start: admin token written to {path} (mode 0600)\n"
            f"tiltlab: dashboard: {shown}",
            file=sys.stderr,
            flush=True,
        )
        return
    first = store.tokens.first_admin_token()
    if path.exists():
        where = f"token: the admin token in {path}"
    elif first is not None:
        where = (
            f"token: the lab's first admin token, which node {first.node} wrote to {first.file} "
            "at its first start, or one of `tiltlab token create`"
        )
    else:
        where = "token: one of `tiltlab token create`"
    print(f"tiltlab: dashboard: {url} ({where})", file=sys.stderr, flush=True)


def dashboard_url(s: Settings) -> str:
    host = s.host if ":" not in s.host else f"[{s.host}]"
    return f"http://{'127.0.0.1' if host in ('0.0.0.0', '[::]') else host}:{s.port}/"


async def _register(store: Store, bench: BenchRuntime) -> None:
    """Benches and identified instruments get their rows (records and jobs refer to them); daemons
    starting together register each bench and instrument once."""
    row = store.devices.ensure_bench(bench.name, actor="daemon")
    bench.bench_id = row.id
    for role, ident in bench.identities.items():
        # no serial of its own: known by bench, role, address
        serial = ident.register_key(bench.name, role)
        dev = store.devices.ensure_device(
            ident.model, serial, role, actor="daemon", bench_id=row.id, port=bench.port_of(role)
        )
        bench.device_ids[role] = dev.id


async def _start_benches(
    store: Store, runtimes: list[BenchRuntime], calls: DatabaseCalls, engine: sa.Engine
) -> None:
    """Every bench started and registered; if one fails, all are closed, and the database
    released, before the failure is raised."""
    try:
        for bench in runtimes:
            await bench.start()
            await _register(store, bench)
    except BaseException:
        for bench in runtimes:
            await bench.close()
        calls.shutdown()
        engine.dispose()
        raise


def _mark_jobs_left(store: Store, runtimes: list[BenchRuntime], s: Settings) -> None:
    """The jobs the previous run left unfinished marked interrupted (resumable)."""
    # Alone, the daemon's previous run left every unfinished job; a node of a fleet, only its
    # own benches' (other nodes may be running theirs while this one starts).
    own = (
        [runtime.bench_id for runtime in runtimes if runtime.bench_id is not None]
        if s.broker_url
        else None
    )
    left = store.jobs.mark_interrupted(actor="daemon", bench_ids=own)
    if left:
        log.warning(
            "jobs %s were left unfinished by the previous run: marked interrupted (resumable)",
            left,
        )


async def _join_fleet(
    app: FastAPI,
    s: Settings,
    hub: StreamHub,
    jobs: JobManager,
    runtimes: list[BenchRuntime],
    calls: DatabaseCalls,
    engine: sa.Engine,
) -> Fleet:
    """This node in the fleet, its benches claimed; if that fails, everything started so far is
    stopped before the failure is raised."""
    fleet = Fleet(
        s,
        app.state.benches,
        lambda name: hub.producers[name].latest_message,
        partial(run_forwarded, app),
    )
    try:
        await fleet.start()
    except BaseException:
        await hub.stop()
        await jobs.shutdown()
        for bench in runtimes:
            await bench.close()
        await app.state.diagnoses.shutdown()
        calls.shutdown()
        engine.dispose()
        raise
    return fleet


def create_app(settings: Settings | None = None) -> FastAPI:
    """The application; unusable settings are refused here (InputError, one line), before
    serving."""
    config = settings or get_settings()
    normalise_url(config.database_url)
    if config.auth == "none" and not is_loopback(config.host):
        raise InputError(
            f"TILTLAB_AUTH=none is refused on {config.host}: without authentication the daemon"
            " binds only a loopback address (127.0.0.1, ::1)"
        )
    _check_benches(config)
    # the access log prints query strings; a WebSocket's may carry its token
    install_log_redaction()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.settings = config
        app.state.engine = engine = bootstrap(config)  # brings the database to the current schema
        store = app.state.store = Store(engine)
        database = app.state.database = DatabaseState(redacted(engine.url), config.db_outage_s)
        # a request's database work: in threads of its own, each call with a deadline (never the
        # event loop)
        calls = app.state.db_calls = DatabaseCalls(
            redacted(engine.url),
            config.db_request_timeout_s,
            config.db_request_threads,
            on_timeout=database.away,
        )
        app.state.token_checks = TokenChecks(
            store.tokens.authenticate,
            calls,
            database,
            throttle=FailedTokens(config.failed_tokens_burst, config.failed_tokens_every_s),
        )
        # /health and /ready ask the database at most once a second (and so notice it going away)
        app.state.schema_revision = SchemaRevision(database=database)
        lost = store.diagnoses.mark_diagnoses_interrupted(actor="daemon")
        if lost:
            log.warning(
                "diagnoses %s were left unfinished by the previous run: marked failed", lost
            )
        announce_dashboard(store, config, terminal=sys.stderr.isatty())
        runtimes = plan_benches(config)
        await _start_benches(store, runtimes, calls, engine)
        _mark_jobs_left(store, runtimes, config)
        app.state.benches = {runtime.name: runtime for runtime in runtimes}
        app.state.bench = runtimes[0]
        disk = app.state.disk = DiskWatch(
            folders_of(config.data_dir, config.database_url), config.min_free_mb
        )
        jobs = app.state.jobs = JobManager(
            store, app.state.benches, database, disk, require_conditions=config.require_conditions
        )
        for bench in runtimes:
            jobs.load_active(bench)
        # the workflow on stored points, in a worker process: never the bench, never the event loop
        app.state.diagnoses = DiagnosisRunner(store, jobs, max_diagnoses=config.max_diagnoses)
        hub = app.state.streams = StreamHub(
            app.state.benches,
            jobs,
            queue_size=config.stream_queue_size,
            slow_close_s=config.stream_slow_close_s,
            snapshots=SnapshotGate(config.max_snapshots, config.snapshot_queue),
        )
        hub.start()  # one reading producer per bench
        metrics.sources.update(
            {
                "benches": app.state.benches,
                "streams": hub,
                "writes_in_flight": writes_in_flight,
                "database": database,
            }
        )
        app.state.fleet = fleet = None
        # joins the fleet: claims this node's benches (exit 2 if a live node owns one)
        if config.broker_url:
            fleet = await _join_fleet(app, config, hub, jobs, runtimes, calls, engine)
            app.state.fleet = hub.remote = fleet
        # webhook deliveries from the outbox, reference standards coming due
        lims = LimsRuntime(store, config)
        app.state.webhooks = lims.dispatcher
        await lims.start()
        log.info(
            "tiltlab %s: database %s, benches %s",
            __version__,
            engine.url,
            ", ".join(app.state.benches),
        )
        try:
            yield
        finally:
            if fleet is not None:
                await fleet.stop()
            await hub.stop()
            await lims.stop()
            await jobs.shutdown()
            await app.state.diagnoses.shutdown()
            for bench in runtimes:
                await bench.close()
            calls.shutdown()
            engine.dispose()

    # /docs and /redoc with their scripts and styles served from the installed package, not a CDN:
    # lab networks are often air-gapped.
    app = FastAPIOffline(
        title="tiltlab",
        version=__version__,
        lifespan=lifespan,
        static_url="/docs-assets",
        description="Calibration, measurement and control of tilt with biaxial inclinometers. "
        "Every route but /health, /ready and the dashboard needs `Authorization: Bearer"
        " <token>` (scopes read, operate, admin). Errors are RFC 9457 problem+json (the `Problem`"
        " schema).",
    )
    app.state.metrics = metrics = Metrics()
    app.add_middleware(FleetRouting)
    # the token before anything else looks at a request (the fleet's forwarding, the routing table)
    app.add_middleware(Authentication, state_of=app)
    # outside the token check and every route: a large body is refused unread, with or without a
    # token
    app.add_middleware(BodySizeLimit, max_bytes=config.max_body_bytes)
    app.add_middleware(MetricsMiddleware, metrics=metrics)
    problems.install(app)  # with the one mapping of an unknown entity to 404
    openapi.install(app)
    http_details.install(app)
    app.add_middleware(ContentSecurity)  # every HTML page with its Content-Security-Policy
    # outermost of ours: the polled route's plain case
    app.add_middleware(PreparedTilt, state_of=app)
    redoc.install(app, "/docs-assets")
    _install_errors(app)
    for router_module in (
        health,
        metrics_router,
        benches,
        tilt,
        stage,
        stage_home,
        calibrations,
        records,
        diagnoses,
        lims,
        streams,
        tokens,
    ):
        app.include_router(router_module.router)
    dashboard.install(app)
    return app


def _install_errors(app: FastAPI) -> None:
    problem = problems.problem

    @app.exception_handler(RequestProblem)
    async def _request(request: Request, exc: RequestProblem) -> Response:
        return problem(
            exc.status,
            "Unusable request" if exc.status == 422 else "Conflict",
            str(exc),
            instance=str(request.url.path),
            field=exc.field,
        )

    for cls, status, title, field in _ERRORS:
        app.add_exception_handler(cls, _answer(status, title, field))

    @app.exception_handler(DiagnosesBusy)
    async def _diagnoses_busy(request: Request, exc: DiagnosesBusy) -> Response:
        answer = problem(503, "Diagnoses busy", str(exc), instance=str(request.url.path))
        answer.headers["Retry-After"] = str(DIAGNOSES_RETRY_AFTER_S)
        return answer

    async def _disk(request: Request, exc: Exception) -> Response:
        """A full disk: 507 naming it; nothing was stored (the request may be made again once there
        is room)."""
        disk = getattr(request.app.state, "disk", None)
        said = disk.described(exc) if isinstance(disk, DiskWatch) else f"disk full: {exc}"
        return problem(
            507,
            "Insufficient Storage",
            f"{said}; nothing was stored: free space and ask again",
            instance=str(request.url.path),
        )

    app.add_exception_handler(DiskFull, _disk)

    @app.exception_handler(OSError)
    async def _os_error(request: Request, exc: OSError) -> Response:
        if disk_full(exc):
            return await _disk(request, exc)
        return problem(
            500,
            "Internal Server Error",
            f"the service failed on this request ({type(exc).__name__});"
            " the service log has the details",
            instance=str(request.url.path),
        )

    async def _database(request: Request, exc: Exception) -> Response:
        """The database away: 503 naming it (the request may be asked again once it answers); a full
        disk (the daemon's, or the database server's): 507; any other database error is the server's
        own (500)."""
        if disk_full(exc):
            return await _disk(request, exc)
        if not unreachable(exc):
            raise exc
        state = getattr(request.app.state, "database", None)
        where = redacted(request.app.state.engine.url)
        if isinstance(state, DatabaseState) and not isinstance(exc, DatabaseOutage):
            state.away(exc)
        answer = problems.problem(
            503,
            "Database unreachable",
            f"the database {where} does not answer, so this request could not be carried out"
            " (if the database went away while it was written, it may have been); ask again"
            " once it answers (GET /health says when)",
            instance=str(request.url.path),
        )
        answer.headers["Retry-After"] = "5"
        return answer

    app.add_exception_handler(sa.exc.DBAPIError, _database)
    app.add_exception_handler(DatabaseOutage, _database)


# Our exceptions as problems: (class, status, title, the field at fault if one is).
_ERRORS = (
    (IdempotencyMismatch, 422, "Idempotency-Key reused", "Idempotency-Key"),
    (BenchBusy, 409, "Bench busy", "bench"),
    (ConflictError, 409, "Conflict", None),
    (DeviceNotAnswering, 503, "Device not answering", None),
    (StageNotHomed, 409, "Stage not homed", None),
    (MotionStopped, 409, "Motion stopped", None),
    (DeviceError, 503, "Device error", None),
    (TimeoutError, 503, "Device did not settle", None),
)


def _answer(
    status: int, title: str, field: str | None
) -> Callable[[Request, Exception], Awaitable[Response]]:
    async def handler(request: Request, exc: Exception) -> Response:
        extra = {"field": field} if field else {}
        return problems.problem(status, title, str(exc), instance=str(request.url.path), **extra)

    return handler
