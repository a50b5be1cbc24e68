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

from tests.helpers.running_service import serving


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
    log = tmp / "daemon.log"
    with serving((), env, log, timeout_s=90, healthy=True) as (proc, port, base):
        yield Daemon(proc, base, port, made.stdout.strip(), log, env)
