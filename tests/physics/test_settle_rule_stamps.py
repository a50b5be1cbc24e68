"""The drift settle rule (`tolerance_deg` between two windows) is judged at the readings' own
stamps: the bench time it returns is a reading's stamp, the same however often, and how late, the
daemon looks. A sped-up simulator on a busy machine looks late in bench time; a real bench's daemon
looks late under load. Neither may count as settling, nor may the daemon's lateness in beginning
to look: given the stage's stop, the rule takes the readings since then."""

from __future__ import annotations

import asyncio
import datetime as dt

import numpy as np
import pytest

from service.bench.readings import settle
from service.instruments.base import Reading

RATE_HZ = 25.0
TAU_S = 0.6
MOVE_DEG = 2.0
SIGMA_DEG = 0.0005


class FakeClock:
    """Bench time that advances only when the waiting code sleeps, by `lag` times what it asked."""

    def __init__(self, lag: float) -> None:
        self.now, self.lag = 0.0, lag

    def monotonic(self) -> float:
        return self.now

    async def sleep(self, bench_s: float) -> None:
        self.now += bench_s * self.lag
        await asyncio.sleep(0)


class FakeBench:
    """Two sensors reading a first-order approach to a new tilt, stamped at their output rate; a
    reading exists once the clock has passed its stamp."""

    def __init__(self, lag: float, seed: int, looks_from_s: float = 0.0) -> None:
        self.clock = FakeClock(lag)
        self.clock.now = looks_from_s  # when the daemon begins to look (the stage stopped at 0)
        rng = np.random.default_rng(seed)
        t = np.arange(1, int(20 * RATE_HZ)) / RATE_HZ
        self.stamps = t
        self.values = {
            role: MOVE_DEG * np.exp(-t / TAU_S)[:, None] + rng.normal(0, SIGMA_DEG, (t.size, 2))
            for role in ("reference_sensor", "measurement_sensor")
        }

    async def sync(self, roles: tuple[str, ...]) -> float:
        return self.clock.now

    def require(self, role: str) -> None:
        assert role in self.values

    def output_interval_s(self, role: str) -> float:
        return 1.0 / RATE_HZ

    def readings_after(self, role: str, after_s: float) -> list[Reading]:
        t0 = dt.datetime(2026, 1, 1, tzinfo=dt.UTC)
        pick = (self.stamps > after_s) & (self.stamps <= self.clock.now)
        return [
            Reading(role, float(t), t0, x_deg=float(v[0]), y_deg=float(v[1]))
            for t, v in zip(self.stamps[pick], self.values[role][pick])
        ]


def _settled_at(
    lag: float, seed: int, looks_from_s: float = 0.0, since_bench_s: float | None = None
) -> float:
    bench = FakeBench(lag, seed, looks_from_s)
    return asyncio.run(
        settle(
            bench,  # type: ignore[arg-type]
            tuple(bench.values),
            tolerance_deg=0.001,
            window_s=0.5,
            timeout_s=30,
            since_bench_s=since_bench_s,
        )
    )


@pytest.mark.parametrize("seed", range(3))
def test_the_settled_time_is_a_reading_stamp_whatever_the_polling(seed):
    prompt = _settled_at(1.0, seed)
    # looking 3 and 17 times later than asked (a busy machine, a fast simulation)
    assert _settled_at(3.0, seed) == prompt == _settled_at(17.0, seed)
    assert prompt in FakeBench(1.0, seed).stamps

    # and it is where the rule says: the two windows ending there agree within the tolerance, the
    # transient's own step between them (about MOVE e^(-t/tau) (1 - e^(-0.5/tau))) at most about it
    def step(at: float) -> float:
        return MOVE_DEG * np.exp(-(at - 0.5) / TAU_S) * (1 - np.exp(-0.5 / TAU_S))

    noise = 4 * SIGMA_DEG * np.sqrt(2 / (0.5 * RATE_HZ))  # 4 sd of the difference of two means
    assert step(prompt) < 0.001 + noise, prompt
    # and not much later than needed: a second earlier the transient still moved the windows apart
    assert step(prompt - 1.0) > 0.001 - noise, prompt


@pytest.mark.parametrize("seed", range(3))
def test_a_daemon_that_begins_to_look_late_settles_at_the_same_stamp_given_the_stop(seed):
    prompt = _settled_at(1.0, seed)
    # the daemon begins to look only once the transient is over (a loaded machine running a
    # sped-up bench): from the stop, the same reading; from when it began to look, two windows later
    late_s = prompt + 0.2
    assert _settled_at(1.0, seed, looks_from_s=late_s, since_bench_s=0.0) == prompt
    assert _settled_at(3.0, seed, looks_from_s=late_s, since_bench_s=0.0) == prompt
    assert _settled_at(1.0, seed, looks_from_s=late_s) >= late_s + 2 * 0.5
