"""The console script run as people run it: `tiltlab ARGS` in a folder, its output captured."""

from __future__ import annotations

import subprocess
import sys


def tiltlab(*args, cwd):
    return subprocess.run(
        [sys.executable, "-m", "service", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
    )
