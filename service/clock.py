"""The one clock of the daemon, its jobs and the simulated instruments (shared by every layer, hence
the root).

Bench time (`monotonic`) is what motion, settling, output intervals and sample times are
measured in. On real hardware it is the process's monotonic clock; a simulated bench may
run `speed` times faster, and then every party that shares this clock (simulated firmware,
drivers' timeouts of bench operations, settling windows of a job) is sped up alike, so a
2-hour calibration can be rehearsed in minutes without changing a single rule. Wall-clock
UTC (`utc`) is never scaled: records, audit events and API times are real times.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import math
import time


class Clock:
    """Bench time that runs `speed` times faster than real time (1.0 on hardware)."""

    def __init__(self, speed: float = 1.0) -> None:
        if (
            isinstance(speed, bool)
            or not isinstance(speed, int | float)
            or not math.isfinite(speed)
            or speed <= 0
        ):
            raise ValueError(f"clock speed {speed!r} must be a finite number > 0")
        self.speed = float(speed)
        self._real0 = time.monotonic()

    def monotonic(self) -> float:
        """Bench seconds since the clock was made."""
        return (time.monotonic() - self._real0) * self.speed

    def real_seconds(self, bench_s: float) -> float:
        """How long `bench_s` bench seconds take in real time."""
        return bench_s / self.speed

    def bench_seconds(self, real_s: float) -> float:
        return real_s * self.speed

    @staticmethod
    def utc() -> dt.datetime:
        return dt.datetime.now(dt.UTC)

    async def sleep(self, bench_s: float) -> None:
        await asyncio.sleep(max(bench_s, 0.0) / self.speed)

    def sleep_blocking(self, bench_s: float) -> None:
        """For threads (simulated firmware, port readers); never call it on the event loop."""
        time.sleep(max(bench_s, 0.0) / self.speed)

    def __repr__(self) -> str:
        return f"Clock(speed={self.speed:g})"


REAL_TIME = Clock(1.0)
