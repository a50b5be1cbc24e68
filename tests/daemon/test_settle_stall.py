"""The statistical settling wait on a machine that stalls: a sped-up simulation that stalls for a
real second loses twenty bench seconds of a sensor's frames; the transient decays meanwhile, and the
wait goes on to judge the readings after the gap instead of timing out on the gap. A sensor that
never settles still times out."""

from __future__ import annotations

import asyncio
import datetime as dt

import numpy as np
import pytest

from service.bench.readings import settle_statistical
from service.clock import Clock
from service.instruments.base import Reading

RATE_HZ = 25.0
NOISE_DEG = 0.001
NOW = dt.datetime(2026, 11, 29, tzinfo=dt.UTC)


class _StallingBench:
    """One sensor whose readings (given with their bench stamps) come a few per look: `per_look`
    readings each time the wait looks."""

    def __init__(self, stamps: np.ndarray, values: np.ndarray, per_look: int = 10) -> None:
        self.clock = Clock(1000.0)  # the wait's sleeps are short in real time
        self.readings = [
            Reading("reference_sensor", float(t), NOW, x_deg=float(v), y_deg=float(v))
            for t, v in zip(stamps, values)
        ]
        self.shown = 0
        self.per_look = per_look

    def require(self, role: str) -> None:
        pass

    def output_interval_s(self, role: str) -> float:
        return 1.0 / RATE_HZ

    def readings_after(self, role: str, bench_s: float) -> list[Reading]:
        self.shown = min(self.shown + self.per_look, len(self.readings))
        return [reading for reading in self.readings[: self.shown] if reading.bench_s > bench_s]


def _wait(bench: _StallingBench):
    return asyncio.run(
        settle_statistical(
            bench,  # type: ignore[arg-type]
            ("reference_sensor",),
            {"reference_sensor": NOISE_DEG},
            timeout_s=30.0,
            since_bench_s=0.0,
        )
    )


def test_a_stall_through_the_timeout_does_not_time_the_wait_out():
    """A 1.5 s sensor's lag decaying from 5 deg, read for 10 bench s (still 0.006 deg off); then
    the machine stalls for 35 bench s (no frames) and the readings that follow are settled: the
    wait passes on them."""
    rng = np.random.default_rng()
    before = np.arange(0.0, 10.0, 1.0 / RATE_HZ)
    after = 45.0 + np.arange(0.0, 10.0, 1.0 / RATE_HZ)
    stamps = np.concatenate([before, after])
    values = 5.0 * np.exp(-stamps / 1.5) + rng.normal(0.0, NOISE_DEG, stamps.size)
    settled = _wait(_StallingBench(stamps, values))
    assert settled.bench_s > 45.0


def test_a_sensor_that_keeps_drifting_times_out():
    rng = np.random.default_rng()
    stamps = np.arange(0.0, 60.0, 1.0 / RATE_HZ)
    # 0.05 deg/s: block means always further apart than the noise allows
    values = 0.05 * stamps + rng.normal(0.0, NOISE_DEG, stamps.size)
    with pytest.raises(TimeoutError, match="reference_sensor did not settle"):
        _wait(_StallingBench(stamps, values))
