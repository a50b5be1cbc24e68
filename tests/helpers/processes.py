"""Processes a test starts (daemons, simulators, writers) end with the test run that started them.

A test stops what it started in a `finally`; but when the test run itself is killed (a CI timeout,
a Ctrl-C twice, an xdist worker that dies) no `finally` runs, and a sped-up daemon left behind
loads the machine for every run after it. So each child is started with Linux's parent-death
signal: it gets SIGTERM the moment the process that started it ends, however that ends.
"""

from __future__ import annotations

import ctypes
import signal
import subprocess
import sys
from typing import Any

_PR_SET_PDEATHSIG = 1


def _term_when_parent_dies() -> None:  # runs in the child, between fork and exec
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


def spawn(*args: Any, **kwargs: Any) -> subprocess.Popen[Any]:
    """`subprocess.Popen`, the child ending when this test process ends (on Linux)."""
    if sys.platform.startswith("linux") and "preexec_fn" not in kwargs:
        kwargs["preexec_fn"] = _term_when_parent_dies
    return subprocess.Popen(*args, **kwargs)
