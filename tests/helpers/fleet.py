"""A NATS server of the test's own, a PostgreSQL schema of its own, and daemons started as people
start them."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.helpers.postgres import fresh_schema_url
from tests.helpers.processes import spawn
from tests.helpers.running_service import free_port
from tests.helpers.waiting import eventually

# what a probe of a daemon, a broker or a database may meet while it is starting, cut or away
UNREACHABLE = (httpx.TransportError, OSError)


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
        self.proc = spawn(
            [self.binary, "-a", "127.0.0.1", "-p", str(self.port), "-js", "-sd", str(self.store)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )

        def listens() -> bool:
            with (
                contextlib.suppress(OSError),
                socket.create_connection(("127.0.0.1", self.port), timeout=1),
            ):
                return True
            assert self.proc is not None and self.proc.poll() is None, "nats-server exited"
            return False

        eventually(listens, timeout_s=20, every_s=0.1, what="nats-server listening")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=20)
        self.proc = None


@contextlib.contextmanager
def postgres_schema_url() -> Iterator[str]:
    """A fresh schema in the test database, dropped afterwards (its sessions ended first: a killed
    daemon's connection must not hold the drop)."""
    with fresh_schema_url("tiltlab_fleet") as url:
        yield url


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
        self.proc = spawn(
            [sys.executable, "-m", "service", "serve", "--port", str(self.port)],
            env={**os.environ, "TILTLAB_DATA_DIR": str(self.data_dir), **self.env},
            stdout=self._log,
            stderr=subprocess.STDOUT,
            text=True,
        )
        return self

    def wait_serving(self, timeout_s: float = 90.0) -> Daemon:
        """Once /health answers; its log in the assertion if the process ended or never answered."""
        proc = self.proc
        assert proc is not None

        def serving() -> bool:
            assert proc.poll() is None, f"daemon did not start: {self.log.read_text()[-3000:]}"
            return httpx.get(f"{self.url}/health", timeout=2).status_code == 200

        try:
            eventually(
                serving,
                timeout_s=timeout_s,
                every_s=0.2,
                ignoring=(httpx.TransportError,),
                what=lambda: f"daemon serving; its log: {self.log.read_text()[-3000:]}",
            )
        except AssertionError:
            self.__exit__(None, None, None)
            raise
        return self

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
