"""`tiltlab serve` as people start it, in a subprocess whose whole output goes to a log file, its
admin token made beforehand by `tiltlab token create` (so the first start prints none)."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx

from tests.helpers.processes import spawn
from tests.helpers.running_service import free_port
from tests.helpers.waiting import eventually


@dataclass
class Daemon:
    proc: subprocess.Popen[bytes]
    base: str
    port: int
    token: str
    log: Path
    env: dict[str, str]

    def rss_kb(self, field: str = "VmRSS") -> int:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
        raise AssertionError(f"no {field} for the daemon")


def tiltlab_cli(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    """`tiltlab ARGS` with the environment `env`; its output captured."""
    return subprocess.run(
        [sys.executable, "-m", "service", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


@contextlib.contextmanager
def logged_daemon(tmp: Path, **settings: str) -> Iterator[Daemon]:
    """A daemon on the data directory tmp/data with the settings (environment variables) given,
    once /health answers; its log at tmp/daemon.log."""
    env = {
        **os.environ,
        "TILTLAB_DATA_DIR": str(tmp / "data"),
        "TILTLAB_SIM_SPEED": "10",
        **settings,
    }
    env.pop("TILTLAB_CONFIG", None)
    made = tiltlab_cli(env, "token", "create", "--name", "lims", "--scopes", "admin")
    assert made.returncode == 0, made.stderr
    port = free_port()
    log = tmp / "daemon.log"
    with log.open("wb") as out:
        proc = spawn(
            [sys.executable, "-m", "service", "serve", "--port", str(port)],
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    base = f"http://127.0.0.1:{port}"

    def serving() -> bool:
        assert proc.poll() is None, log.read_text()
        return httpx.get(f"{base}/health", timeout=2).status_code == 200

    try:
        eventually(
            serving,
            timeout_s=90,
            every_s=0.2,
            ignoring=(httpx.TransportError,),
            what=lambda: f"the daemon answering /health; its log: {log.read_text()}",
        )
        yield Daemon(proc, base, port, made.stdout.strip(), log, env)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
