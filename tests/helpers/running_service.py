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
def running_service(data_dir: Path, args: Sequence[str] = (), **env: str) -> Iterator[str]:
    """Start the service on an empty data directory (with `tiltlab serve` options `args`); yields
    its base URL once /health answers."""
    port = free_port()
    # the daemon's output goes to a file beside the data directory: a pipe nobody reads fills after
    # 64 kB of access log and then holds the daemon's event loop on its next log line
    log = Path(data_dir).parent / f"{Path(data_dir).name}.serve.log"
    with log.open("wb") as out:
        proc = spawn(
            [sys.executable, "-m", "service", "serve", "--port", str(port), *args],
            env={**os.environ, "TILTLAB_DATA_DIR": str(data_dir), **env},
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    base = f"http://127.0.0.1:{port}"

    def answers() -> bool:
        assert proc.poll() is None, f"service did not start: {log.read_text(errors='replace')}"
        httpx.get(f"{base}/health", timeout=2)
        return True

    try:
        eventually(
            answers,
            timeout_s=60,
            every_s=0.2,
            ignoring=(httpx.TransportError,),
            what=lambda: f"service answering /health; its log: {log.read_text(errors='replace')}",
        )
        yield base
    finally:
        proc.terminate()
        proc.wait(timeout=20)
