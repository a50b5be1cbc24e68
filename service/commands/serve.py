"""`tiltlab serve`: check the settings, bind, reach the database, start, and only then announce.

Every start-up failure is one line naming the setting and what to do: exit 2 when a setting can
never work (port out of range, unknown host address, unwritable data directory, unusable bench
scenario or database URL, credentials refused), exit 1 when the surroundings are at fault and
may mend (port held by another program, database not answering within TILTLAB_DATABASE_WAIT_S).
"""

from __future__ import annotations

import argparse
import errno
import logging
import socket
import sys
from collections.abc import AsyncIterator, Mapping
from contextlib import asynccontextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.commands._args import add_command, port, seconds, speed
from service.errors import InputError

if TYPE_CHECKING:
    from service.config import Settings

SWITCH_INTERVAL_S = 0.001


class StartupFailure(RuntimeError):
    """The service cannot start for a reason outside its settings (exit 1)."""


def _say(text: str) -> None:
    print(f"tiltlab serve: {text}", file=sys.stderr, flush=True)


def bind_socket(host: str, port: int) -> socket.socket:
    """A listening-ready socket on host:port, or a one-line error naming --host/--port."""
    from service.api.limits import bound_send_buffer

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise InputError(
            f"--host {host} (TILTLAB_HOST): not an address of this machine ({exc.strerror}); "
            "give 127.0.0.1 for this computer only, or 0.0.0.0 for every network"
        ) from None
    family, kind, proto, _, address = infos[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        # every connection's send buffer: how much a stalled stream client can hold
        bound_send_buffer(sock)
        sock.bind(address)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise StartupFailure(
                f"--port {port} (TILTLAB_PORT): {host}:{port} is already in use by another "
                "program; stop it, or choose another port with --port"
            ) from None
        if exc.errno == errno.EACCES:
            raise InputError(
                f"--port {port} (TILTLAB_PORT): this user may not listen on {host}:{port} "
                "(ports below 1024 need privileges); choose a port of 1024 or above"
            ) from None
        if exc.errno == errno.EADDRNOTAVAIL:
            raise InputError(
                f"--host {host} (TILTLAB_HOST): not an address of this machine; "
                "give 127.0.0.1, 0.0.0.0 or one of this machine's addresses"
            ) from None
        raise StartupFailure(
            f"--host {host} --port {port}: cannot listen ({exc.strerror})"
        ) from None
    sock.set_inheritable(True)
    return sock


def _prepare_database(settings: Any) -> None:
    """Wait for the database (with back-off) and bring it to the current schema, before serving."""
    from alembic.util.exc import CommandError

    from service.storage.engine import make_engine
    from service.storage.migrate import upgrade
    from service.storage.reachable import DatabaseUnreachable, wait_for_database

    engine = make_engine(settings.database_url, busy_timeout_ms=settings.sqlite_busy_timeout_ms)
    try:
        wait_for_database(engine, settings.database_wait_s, _say)
        try:
            upgrade(engine)
        except CommandError as exc:
            raise InputError(
                "TILTLAB_DATABASE_URL: the database's schema is not one this tiltlab knows "
                f"({exc}); "
                "it was written by a newer tiltlab: run that version, or restore a backup"
            ) from None
    except DatabaseUnreachable as exc:
        raise StartupFailure(str(exc)) from None
    finally:
        engine.dispose()


class _StartupGuard(logging.Filter):
    """Until start-up succeeds, the application's start-up traceback is ours to report in one
    line."""

    def __init__(self) -> None:
        super().__init__()
        self.failure: BaseException | None = None
        self.active = True

    def filter(self, record: logging.LogRecord) -> bool:
        if self.active and self.failure is not None:
            return False
        return True


def _guard_lifespan(app: Any, guard: _StartupGuard) -> None:
    inner = app.router.lifespan_context

    @asynccontextmanager
    async def guarded(a: Any) -> AsyncIterator[Any]:
        entered = False
        try:
            async with inner(a) as state:
                entered = True
                yield state
        except Exception as exc:
            if not entered:
                guard.failure = exc
            raise

    app.router.lifespan_context = guarded


def _with_overrides(settings: Settings, args: argparse.Namespace) -> Settings:
    """The settings with the command-line options that were given in place of the environment's,
    validated like it (one line naming the setting)."""
    overrides = {
        name: getattr(args, name, None)
        for name in (
            "host",
            "port",
            "database_wait_s",
            "sim_speed",
            "bench_config",
            "bench_scenario",
        )
    }
    overrides = {name: value for name, value in overrides.items() if value is not None}
    if overrides:
        settings = type(settings)(**overrides)
    return settings


def _tls_refusal(tls: Mapping[str, str | None]) -> str | None:
    """Why the TLS options cannot work (one of the pair alone, a file missing), or None."""
    if bool(tls["ssl_certfile"]) != bool(tls["ssl_keyfile"]):
        return "--ssl-certfile and --ssl-keyfile go together: give both, or neither for plain HTTP"
    for opt, path in tls.items():
        if path and not Path(path).is_file():
            return f"--{opt.replace('_', '-')} {path}: no such file"
    return None


def _startup_failed(failure: BaseException | None) -> int:
    """Say in one line why the application did not start; exit 2 for a setting, else 1."""
    reason = (
        f"{type(failure).__name__}: {failure}"
        if failure is not None
        else "the application did not start"
    )
    _say(f"start-up failed: {' '.join(reason.split())}")
    return 2 if isinstance(failure, InputError) else 1


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from service.api.app import create_app
    from service.api.server import protocols
    from service.config import ensure_data_dir, get_settings

    # The event loop (every request, the streams) gets the interpreter back within 1 ms of asking,
    # not 5 ms (Python's default), while request threads decode a page of records or build a
    # snapshot.
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    settings = _with_overrides(get_settings(), args)
    host, port = settings.host, settings.port
    tls: dict[str, str | None] = {  # uvicorn's option: the file (None: plain HTTP)
        "ssl_certfile": getattr(args, "ssl_certfile", None),
        "ssl_keyfile": getattr(args, "ssl_keyfile", None),
    }
    refusal = _tls_refusal(tls)
    if refusal is not None:
        _say(refusal)
        return 2
    scheme = "https" if tls["ssl_certfile"] else "http"
    try:
        ensure_data_dir(settings)
        app = create_app(settings)  # refuses an unusable bench scenario or database URL
        sock = bind_socket(host, port)
    except StartupFailure as exc:
        _say(str(exc))
        return 1
    try:
        try:
            _prepare_database(settings)
        except StartupFailure as exc:
            _say(str(exc))
            return 1
        guard = _StartupGuard()
        _guard_lifespan(app, guard)
        logging.getLogger("uvicorn.error").addFilter(guard)
        announced: list[bool] = []

        class _Server(uvicorn.Server):
            async def startup(self, sockets: list[socket.socket] | None = None) -> None:
                try:
                    await super().startup(sockets=sockets)
                except SystemExit:  # the application failed to start; the guard holds why
                    self.should_exit = True
                    return
                guard.active = False
                shown = f"[{host}]" if ":" in host else host
                _say(f"serving on {scheme}://{shown}:{port} (data in {settings.data_dir})")
                for line in silent_devices(app):
                    _say(line)
                announced.append(True)

        # uvicorn's own HTTP and WebSocket protocols with the limits a request meets before it is
        # parsed
        http_protocol, ws_protocol = protocols(settings)
        # no per-message compression of WebSocket messages: it runs on the event loop (a snapshot's
        # megabytes of history would hold every other request for tens of ms), and the readings'
        # small messages gain little
        server = _Server(
            uvicorn.Config(
                app,
                log_level="info",
                lifespan="on",
                http=http_protocol,
                ws=ws_protocol,
                ws_per_message_deflate=False,
                # a file not given is uvicorn's default (None: plain HTTP)
                ssl_certfile=tls["ssl_certfile"] or None,
                ssl_keyfile=tls["ssl_keyfile"] or None,
            )
        )
        try:
            server.run(sockets=[sock])
        except KeyboardInterrupt:  # Ctrl-C after a clean shutdown
            if announced:
                _say("stopped")
                return 0
            raise
        if not announced:
            return _startup_failed(guard.failure)
        return 0
    finally:
        sock.close()


def silent_devices(app: Any) -> list[str]:
    """One line per instrument that did not answer at start-up (not connected, or it never
    identified itself), naming bench, role and port: a bench of dead ports must not start in
    silence."""
    lines = []
    for bench in app.state.benches.values():
        for st in bench.devices.status():
            if st.state == "connected" and st.role in bench.identities:
                continue
            why = st.state if st.state != "connected" else "connected but did not identify itself"
            lines.append(
                f"bench {bench.name}: {st.role} on {st.port} does not answer ({why}"
                + (f": {st.error}" if st.error else "")
                + "); GET /ready lists what is not ready"
            )
    return lines


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = add_command(
        sub,
        "serve",
        "run the lab service: HTTP API and dashboard on a simulated or real bench",
        description="Run the lab service. Settings come from TILTLAB_* environment variables or "
        "the TOML file named\nby TILTLAB_CONFIG (docs/storage.md); the options below "
        "override them. Start-up failures\nare one line: exit 2 for a setting that "
        "cannot work, 1 when the surroundings are at fault.",
        examples=[
            "tiltlab serve",
            "tiltlab serve --host 0.0.0.0 --port 8080",
            "tiltlab serve --sim-speed 20 --scenario seed000-worm",
            "tiltlab serve --bench-config bench.toml",
        ],
    )
    parser.add_argument(
        "--host",
        default=None,
        help="address to listen on (default: TILTLAB_HOST, else 127.0.0.1: this computer only)",
    )
    parser.add_argument(
        "--port", type=port, default=None, help="TCP port (default: TILTLAB_PORT, else 8000)"
    )
    parser.add_argument(
        "--database-wait-s",
        type=seconds,
        default=None,
        metavar="SECONDS",
        help="how long to retry an unreachable database at start-up "
        "(default: TILTLAB_DATABASE_WAIT_S, else 30)",
    )
    parser.add_argument(
        "--sim-speed",
        type=speed,
        default=None,
        metavar="N",
        help="run the simulated bench N times faster than real time (default: TILTLAB_SIM_SPEED, "
        "else 1)",
    )
    parser.add_argument(
        "--scenario",
        dest="bench_scenario",
        default=None,
        metavar="NAME_OR_FILE",
        help="the simulated stage bench: a preset (tiltlab simulate --list) or a scenario file "
        "(default: TILTLAB_BENCH_SCENARIO, else seed000)",
    )
    parser.add_argument(
        "--bench-config",
        default=None,
        metavar="FILE",
        help="bench configuration (TOML) naming the instruments' ports "
        "(default: TILTLAB_BENCH_CONFIG, else the simulated stage bench)",
    )
    parser.add_argument(
        "--ssl-certfile",
        default=None,
        metavar="FILE",
        help="serve HTTPS with this certificate (PEM; with --ssl-keyfile): tokens then never "
        "cross the network in clear",
    )
    parser.add_argument(
        "--ssl-keyfile", default=None, metavar="FILE", help="the certificate's private key (PEM)"
    )
    parser.set_defaults(handler=run)
