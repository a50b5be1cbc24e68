"""One way for a test to wait: a condition polled until it holds or its deadline passes.

The deadline bounds a wait, it is not a measurement: a test never asserts on how long something
took.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def eventually(
    condition: Callable[[], T], *, timeout_s: float = 30.0, every_s: float = 0.01, what: str = ""
) -> T:
    """The condition's first true value; an AssertionError naming `what` (and the last value) if
    none comes in time."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() >= deadline:
            raise AssertionError(
                f"never happened within {timeout_s:g} s: {what or condition!r} (last: {value!r})"
            )
        time.sleep(every_s)
