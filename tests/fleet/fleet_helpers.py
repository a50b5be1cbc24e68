"""A NATS server of the test's own, a PostgreSQL schema of its own, and daemons started as people
start them."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import httpx
import pytest
import sqlalchemy as sa

from tests.api.running_service import free_port

PG_URL = os.environ.get(
    "TILTLAB_TEST_POSTGRES_URL", "postgresql+psycopg://root@127.0.0.1:5432/test"
)
T = TypeVar("T")


def eventually(
    probe: Callable[[], T], ok: Callable[[T], Any], timeout_s: float = 30.0, every_s: float = 0.2
) -> T:
    """Probe until `ok` holds; the last value otherwise, in the assertion."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            value = probe()
        except (httpx.TransportError, OSError) as exc:
            value = exc  # type: ignore[assignment]
        else:
            if ok(value):
                return value
        assert time.monotonic() < deadline, f"not within {timeout_s:g} s; last: {value!r}"
        time.sleep(every_s)


class NatsServer:
    """`nats-server -js` on a port of its own with its storage in a directory of the test's;
    restartable."""

    def __init__(self, store: Path, port: int) -> None:
        self.store, self.port = store, port
        self.proc: subprocess.Popen[bytes] | None = None
        binary = shutil.which("nats-server") or (
            "/usr/sbin/nats-server" if Path("/usr/sbin/nats-server").exists() else None
        )
        if binary is None:
            pytest.skip("nats-server is not installed")
        self.binary = binary

    @property
    def url(self) -> str:
        return f"nats://127.0.0.1:{self.port}"

    def start(self) -> None:
        self.store.mkdir(parents=True, exist_ok=True)
        self.proc = subprocess.Popen(
            [self.binary, "-a", "127.0.0.1", "-p", str(self.port), "-js", "-sd", str(self.store)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        deadline = time.monotonic() + 20
        while True:
            with (
                contextlib.suppress(OSError),
                socket.create_connection(("127.0.0.1", self.port), timeout=1),
            ):
                return
            assert self.proc.poll() is None, "nats-server exited"
            assert time.monotonic() < deadline, "nats-server did not listen within 20 s"
            time.sleep(0.1)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=20)
        self.proc = None


@contextlib.contextmanager
def postgres_schema_url() -> Iterator[str]:
    """A fresh schema in the test database, dropped afterwards (its sessions ended first: a killed
    daemon's connection must not hold the drop)."""
    admin = sa.create_engine(PG_URL, connect_args={"connect_timeout": 3})
    try:
        with admin.connect() as conn:
            conn.execute(sa.text("SELECT 1"))
    except Exception as exc:  # noqa: BLE001 - any failure to connect means "no server here"
        admin.dispose()
        pytest.skip(f"PostgreSQL does not answer: {type(exc).__name__}")
    schema = f"tiltlab_fleet_{uuid.uuid4().hex[:12]}"
    with admin.begin() as conn:
        conn.execute(sa.text(f'CREATE SCHEMA "{schema}"'))
    url = sa.make_url(PG_URL).update_query_dict(
        {"options": f"-csearch_path={schema}", "application_name": schema}
    )
    try:
        yield url.render_as_string(hide_password=False)
    finally:
        with admin.begin() as conn:
            conn.execute(
                sa.text(
                    "SELECT pg_terminate_backend(pid) FROM pg_stat_activity"
                    " WHERE application_name = :schema"
                ),
                {"schema": schema},
            )
            conn.execute(sa.text("SET lock_timeout = '20s'"))
            conn.execute(sa.text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()


class Daemon:
    """`tiltlab serve` in a subprocess with the given settings; its URL once /health answers."""

    def __init__(self, data_dir: Path, env: dict[str, str]) -> None:
        self.data_dir, self.env = data_dir, env
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen[str] | None = None
        self.log = data_dir.with_suffix(".log")

    def __enter__(self) -> Daemon:
        return self.launch().wait_serving()

    def launch(self) -> Daemon:
        """Start the process and return at once (daemons launched one after another start
        together)."""
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self._log = self.log.open("w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "service", "serve", "--port", str(self.port)],
            env={**os.environ, "TILTLAB_DATA_DIR": str(self.data_dir), **self.env},
            stdout=self._log,
            stderr=subprocess.STDOUT,
            text=True,
        )
        return self

    def wait_serving(self, timeout_s: float = 90.0) -> Daemon:
        """Once /health answers; its log in the assertion if the process ended or never answered."""
        assert self.proc is not None
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                if httpx.get(f"{self.url}/health", timeout=2).status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.__exit__(None, None, None)
                raise AssertionError(f"daemon did not start: {self.log.read_text()[-3000:]}")
            time.sleep(0.2)

    def __exit__(self, *exc: object) -> None:
        # the test failed inside: its daemons' last words go into the report
        if exc and exc[0] is not None:
            print(
                f"--- {self.log.name} ---\n" + "\n".join(self.log.read_text().splitlines()[-40:]),
                file=sys.stderr,
            )
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self._log.close()
