"""`tiltlab serve` as people start it, in a subprocess on a free port, for tests that need a real
server."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

import httpx

from tests.helpers.processes import spawn
from tests.helpers.waiting import eventually


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def serving(
    args: Sequence[str],
    env: dict[str, str],
    log: Path,
    *,
    timeout_s: float = 60,
    healthy: bool = False,
) -> Iterator[tuple[subprocess.Popen[bytes], int, str]]:
    """`tiltlab serve ARGS --port P` on a free port with the environment `env`, its whole output in
    `log`; yields the process, its port and its base URL once /health answers (with 200 if
    `healthy`), and stops it."""
    port = free_port()
    # the daemon's output goes to a file: a pipe nobody reads fills after 64 kB of access log and
    # then holds the daemon's event loop on its next log line
    with log.open("wb") as out:
        proc = spawn(
            [sys.executable, "-m", "service", "serve", "--port", str(port), *args],
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    base = f"http://127.0.0.1:{port}"

    def answers() -> bool:
        assert proc.poll() is None, f"service did not start: {log.read_text(errors='replace')}"
        status = httpx.get(f"{base}/health", timeout=2).status_code
        return status == 200 or not healthy

    try:
        eventually(
            answers,
            timeout_s=timeout_s,
            every_s=0.2,
            ignoring=(httpx.TransportError,),
            what=lambda: f"service answering /health; its log: {log.read_text(errors='replace')}",
        )
        yield proc, port, base
    finally:
        proc.terminate()
        proc.wait(timeout=30)


@contextlib.contextmanager
def running_service(data_dir: Path, args: Sequence[str] = (), **env: str) -> Iterator[str]:
    """Start the service on an empty data directory (with `tiltlab serve` options `args`); yields
    its base URL once /health answers."""
    log = Path(data_dir).parent / f"{Path(data_dir).name}.serve.log"
    with serving(args, {**os.environ, "TILTLAB_DATA_DIR": str(data_dir), **env}, log) as (
        _,
        _,
        base,
    ):
        yield base
