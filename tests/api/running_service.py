"""`tiltlab serve` as people start it, in a subprocess on a free port, for tests that need a real
server."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import httpx


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
        proc = subprocess.Popen(
            [sys.executable, "-m", "service", "serve", "--port", str(port), *args],
            env={**os.environ, "TILTLAB_DATA_DIR": str(data_dir), **env},
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                httpx.get(f"{base}/health", timeout=2)
                break
            except httpx.TransportError as exc:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise AssertionError(
                        f"service did not start: {log.read_text(errors='replace')}"
                    ) from exc
                time.sleep(0.2)
        yield base
    finally:
        proc.terminate()
        proc.wait(timeout=20)
