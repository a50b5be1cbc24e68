"""One way for a test to wait: a condition polled until it holds or its deadline passes.

The deadline bounds a wait, it is not a measurement: a test never asserts on how long something
took.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")


def eventually(
    condition: Callable[[], T],
    *,
    timeout_s: float = 30.0,
    every_s: float = 0.01,
    what: str | Callable[[], str] = "",
    until: Callable[[T], Any] | None = None,
    ignoring: tuple[type[BaseException], ...] = (),
) -> T:
    """The condition's first true value; an AssertionError naming `what` (and the last value) if
    none comes in time.

    until: the condition is a probe, and its first value for which `until(value)` holds is returned
    (even a false one, such as an empty list).
    ignoring: exceptions the condition may raise while what it polls is not there yet (a server
    still starting); each counts as a value that does not hold, and the last one is the cause of the
    AssertionError.
    what: a callable is called only if the wait fails, for a message saying how far things got.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        error: BaseException | None = None
        try:
            value = condition()
        except ignoring as exc:
            last: object = exc
            error = exc
        else:
            if until(value) if until is not None else value:
                return value
            last = value
        if time.monotonic() >= deadline:
            said = what() if callable(what) else what
            raise AssertionError(
                f"never happened within {timeout_s:g} s: {said or condition!r} (last: {last!r})"
            ) from error
        time.sleep(every_s)
