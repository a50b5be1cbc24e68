"""Readings the daemon waits for (fresh ones after a move), their settling and their robust mean.

Outlier rule, stated once: a sample whose modified z-score |0.6745 (v - median) / MAD| (Iglewicz
and Hoaglin) exceeds the cut for the point's number of readings on any channel is rejected; the
point's value is the mean of the rest. The cut is the score Gaussian readings alone exceed in 1 % of
points (`OUTLIER_CUTS`, from `benchmarks/outlier_cuts.py`): with few readings the MAD scatters
widely, and Iglewicz and Hoaglin's fixed 3.5 rejected a good reading in a quarter of 10-reading
points, leaving their standard deviations too small (a 95 % interval on such a mean covered 92 %).
"""

from __future__ import annotations

import asyncio
import math
import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from service.bench.runtime import BenchRuntime, DeviceNotAnswering
from service.bench.settled import BLOCK, SettleTest
from service.instruments.base import Reading

OUTLIER_FALSE_RATE = 0.01  # of points of Gaussian readings alone in which the rule rejects one
OUTLIER_RULE = (
    "modified z-score |0.6745 (v - median) / MAD| above the cut for the point's number of "
    "readings on any channel rejects a sample; the cut is the score Gaussian readings alone exceed "
    f"in {OUTLIER_FALSE_RATE:.0%} of points (8.2 for 10 readings of two channels, 4.7 for 60)"
)
# readings: the cut for (1, 2, 3) channels, simulated with 100,000 points each (benchmarks/
# outlier_cuts.py); between two rows the fewer readings' cut holds (the larger: fewer rejections)
OUTLIER_CUTS: dict[int, tuple[float, float, float]] = {
    3: (112.84, 215.24, 316.45),
    4: (16.08, 22.37, 27.65),
    5: (18.77, 26.08, 30.45),
    6: (9.98, 13.01, 14.98),
    7: (10.74, 13.62, 15.79),
    8: (7.94, 9.80, 10.82),
    9: (8.33, 9.81, 11.32),
    10: (6.88, 8.25, 8.92),
    11: (7.15, 8.29, 9.23),
    12: (6.29, 7.26, 7.86),
    13: (6.39, 7.34, 8.07),
    14: (5.87, 6.69, 7.19),
    15: (5.97, 6.79, 7.30),
    16: (5.61, 6.26, 6.75),
    17: (5.66, 6.42, 6.84),
    18: (5.45, 6.04, 6.40),
    19: (5.43, 6.06, 6.42),
    20: (5.25, 5.86, 6.16),
    21: (5.24, 5.84, 6.22),
    22: (5.09, 5.60, 5.94),
    23: (5.10, 5.64, 5.98),
    24: (4.99, 5.49, 5.76),
    25: (5.03, 5.54, 5.80),
    26: (4.93, 5.39, 5.65),
    27: (4.94, 5.38, 5.66),
    28: (4.84, 5.23, 5.54),
    29: (4.86, 5.30, 5.58),
    30: (4.76, 5.22, 5.46),
    35: (4.70, 5.08, 5.31),
    40: (4.60, 4.92, 5.09),
    45: (4.56, 4.84, 5.04),
    50: (4.50, 4.79, 4.94),
    60: (4.41, 4.68, 4.85),
    70: (4.38, 4.63, 4.76),
    80: (4.33, 4.58, 4.73),
    100: (4.30, 4.56, 4.66),
    120: (4.29, 4.51, 4.63),
    150: (4.29, 4.48, 4.59),
    200: (4.29, 4.47, 4.59),
}
TABLED_READINGS = tuple(sorted(OUTLIER_CUTS))  # the rows benchmarks/outlier_cuts.py prints
# a gap between two readings longer than this many output intervals is a stall, not watching
STALL_INTERVALS = 4
# a sensor whose readings do not vary at all (quantised) is taken as this noisy
MIN_NOISE_DEG = 1e-6


def channels(r: Reading) -> tuple[float, ...]:
    # a reading carries all the channels of its sensor: both axes, all three sines, or the counts
    if r.x_deg is not None:
        assert r.y_deg is not None
        return (r.x_deg, r.y_deg)
    if r.sx is not None:
        assert r.sy is not None and r.sz is not None
        return (r.sx, r.sy, r.sz)
    assert r.counts is not None
    return (r.counts,)


async def fresh_readings(
    bench: BenchRuntime, role: str, n: int, *, after_bench_s: float, timeout_s: float
) -> list[Reading]:
    """The next `n` readings of a role stamped after `after_bench_s` (bench seconds). `timeout_s` is
    the longest wait for the next reading: bench time, waited for in real time, and never less than
    2 real seconds (a sped-up simulation on a loaded machine lags its bench clock). Each reading
    that comes starts the wait again, so a slow device still answering is not taken for a silent
    one."""
    out: list[Reading] = []
    last = after_bench_s
    interval = bench.output_interval_s(role)
    timeout_s = max(bench.clock.real_seconds(timeout_s), 2.0)
    deadline = time.monotonic() + timeout_s
    while len(out) < n:
        new = bench.readings_after(role, last)[: n - len(out)]
        if new:
            out += new
            last = new[-1].bench_s
            deadline = time.monotonic() + timeout_s
        elif time.monotonic() > deadline:
            st = bench.devices[role].status
            raise DeviceNotAnswering(
                f"{role} on {st.port}: no reading for {timeout_s:g} s ({st.state}"
                + (f": {st.error}" if st.error else "")
                + ")"
            )
        else:
            await bench.clock.sleep(interval / 2)
    return out


@dataclass
class Averaged:
    mean: tuple[float, ...]
    std: tuple[float | None, ...]
    n_used: int
    n_rejected: int
    temp_c: float | None
    t_start_s: float
    t_end_s: float


def modified_z(samples: NDArray[np.float64]) -> NDArray[np.float64]:
    """|0.6745 (v - median) / MAD| of each sample along the readings axis (-2; 0 where the MAD is 0:
    quantised readings that do not vary)."""
    med = np.median(samples, axis=-2, keepdims=True)
    mad = np.median(np.abs(samples - med), axis=-2, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(mad > 0, 0.6745 * np.abs(samples - med) / mad, 0.0)


def outlier_cut(n: int, n_channels: int) -> float:
    """The modified z-score above which one of `n` readings of `n_channels` channels is rejected:
    none below 3 readings; the table's up to its last row; beyond, that row's cut raised as the
    Gaussian bound on the largest of n x channels scores rises from there."""
    if n < TABLED_READINGS[0]:
        return math.inf
    channels_ = min(max(n_channels, 1), 3)
    below = [row for row in TABLED_READINGS if row <= n]
    cut = OUTLIER_CUTS[below[-1]][channels_ - 1]
    if n > TABLED_READINGS[-1]:

        def bound(readings: int) -> float:
            return float(stats.norm.isf(OUTLIER_FALSE_RATE / (2.0 * readings * channels_)))

        cut += bound(n) - bound(TABLED_READINGS[-1])
    return cut


def robust_mean(readings: list[Reading]) -> Averaged:
    samples = np.array([channels(reading) for reading in readings], dtype=float)
    z = modified_z(samples)
    keep = ~(z > outlier_cut(samples.shape[0], samples.shape[1])).any(axis=1)
    kept = samples[keep]
    temps = [
        reading.temp_c
        for reading, k in zip(readings, np.atleast_1d(keep))
        if k and reading.temp_c is not None
    ]
    std = (
        tuple(float(spread) for spread in kept.std(axis=0, ddof=1))
        if len(kept) > 1
        else (None,) * samples.shape[1]
    )
    return Averaged(
        tuple(float(m) for m in kept.mean(axis=0)),
        std,
        int(keep.sum()),
        int((~keep).sum()),
        float(np.mean(temps)) if temps else None,
        readings[0].bench_s,
        readings[-1].bench_s,
    )


async def settle(
    bench: BenchRuntime,
    roles: tuple[str, ...],
    *,
    tolerance_deg: float,
    window_s: float,
    timeout_s: float,
    since_bench_s: float | None = None,
) -> float:
    """Wait until every role's mean over the last `window_s` differs from its mean over the window
    before by at most `tolerance_deg` on every channel (a drift criterion: reading noise averages
    out).

    Judged at the readings' own stamps, not at the moment the daemon looks: the returned bench time
    is the stamp of the first reading at which every role's windows, ending there, agree. So it is
    what the readings say, whatever the polling interval, the machine's load or the simulation's
    speed (a sped-up bench would otherwise count the daemon's real time between looks as settling).
    `timeout_s` is real seconds, whatever the simulation speed: a loaded machine running a sped-up
    simulation must not run out of it while its bench clock lags. With `since_bench_s` (the stage's
    stop) the readings kept since then count, as if the daemon had watched from the stop: the
    daemon's own lateness in starting to look is not settling (on a loaded machine running a
    sped-up bench it is many bench seconds a point). A reading asked during the move and stamped
    after the stop only makes the windows differ, never agree. Without it, only readings made after
    the call count (`bench.sync`). Raises TimeoutError naming the roles that did not settle,
    DeviceNotAnswering (role and port) as soon as one of them is not connected.
    """
    # without the stop: only readings made after the call, a lagging reader may still hold some
    # from the move
    start = await bench.sync(roles) if since_bench_s is None else since_bench_s
    waited_from = time.monotonic()
    history: dict[str, list[Reading]] = {role: [] for role in roles}
    judged_to = start + 2 * window_s  # windows ending before this are not judged (or did not pass)
    while True:
        for role in roles:
            _gather(bench, role, history[role], start)
        settled_at = _first_settled(history, judged_to, window_s, tolerance_deg)
        if settled_at is not None:
            return settled_at
        # every stamp up to the newest reading all roles have is judged: only later ones are new
        complete_to = min((held[-1].bench_s for held in history.values() if held), default=start)
        judged_to = max(judged_to, complete_to + 1e-9)
        for held in history.values():
            while held and held[0].bench_s < judged_to - 2 * window_s - 1e-9:
                held.pop(0)
        if time.monotonic() - waited_from > timeout_s:
            moving = [
                role
                for role in roles
                if _drifting(history[role], complete_to, window_s, tolerance_deg)
            ]
            raise TimeoutError(
                f"readings of {', '.join(moving or roles)} did not settle within "
                f"{tolerance_deg:g} deg between windows of {window_s:g} s in {timeout_s:g} s"
            )
        await bench.clock.sleep(_poll_interval_s(bench, roles))


def _first_settled(
    history: dict[str, list[Reading]], from_s: float, window_s: float, tolerance_deg: float
) -> float | None:
    """The first reading stamp at or after `from_s`, up to the newest reading every role has, at
    which no role drifts (windows ending at that stamp); None if there is none yet."""
    if any(not held for held in history.values()):
        return None
    complete_to = min(held[-1].bench_s for held in history.values())
    stamps = sorted(
        {x.bench_s for held in history.values() for x in held if from_s <= x.bench_s <= complete_to}
    )
    for at in stamps:
        if not any(_drifting(held, at, window_s, tolerance_deg) for held in history.values()):
            return at
    return None


def _gather(bench: BenchRuntime, role: str, held: list[Reading], start: float) -> None:
    """Append to `held` the role's readings made since the last one held (since `start` at first);
    a sensor lost while waiting fails the wait at once, naming role and port."""
    bench.require(role)
    held += bench.readings_after(role, held[-1].bench_s if held else start)


def _drifting(held: list[Reading], at: float, window_s: float, tolerance_deg: float) -> bool:
    """Whether the mean over the `window_s` ending at `at` differs from the mean over the window
    before by more than `tolerance_deg` on some channel (or either window is still empty)."""
    older = [channels(x) for x in held if at - 2 * window_s <= x.bench_s < at - window_s]
    newer = [channels(x) for x in held if at - window_s <= x.bench_s <= at]
    return bool(
        not older
        or not newer
        or np.abs(np.mean(newer, axis=0) - np.mean(older, axis=0)).max() > tolerance_deg
    )


def _poll_interval_s(bench: BenchRuntime, roles: tuple[str, ...]) -> float:
    """Half the shortest output interval of the roles: how long to wait for their next readings."""
    return min(bench.output_interval_s(role) for role in roles) / 2


class Settled(NamedTuple):
    """Where the statistical settling test passed: the bench time of the reading, and the longest
    block (readings) a role passed with (how long a transient this sensor takes to show)."""

    bench_s: float
    block: int


async def settle_statistical(
    bench: BenchRuntime,
    roles: tuple[str, ...],
    noise_deg: dict[str, float],
    *,
    timeout_s: float,
    since_bench_s: float | None = None,
    block: int = BLOCK,
) -> Settled:
    """Wait until every role's readings since the call pass the statistical settling test
    (service.bench.settled, its blocks at least `block` readings) against its reading noise
    `noise_deg[role]`; returns the bench time of the reading at which the last of them passed, and
    the longest block a role passed with. `timeout_s` is bench time (a transient is bench
    physics); past it, TimeoutError names the roles still moving. DeviceNotAnswering as soon as one
    is not connected.

    With `since_bench_s` (the stage's stop) the test takes the readings kept since then, as if it
    had watched from the stop: the test's blocks grow with the time since the move, and a test
    begun late, with short blocks, would not see what is left of a slow sensor's transient."""
    start = await bench.sync(roles) if since_bench_s is None else since_bench_s
    history: dict[str, list[Reading]] = {role: [] for role in roles}
    passed: dict[str, float] = {}
    blocks: list[int] = []
    checked = dict.fromkeys(roles, 0)
    waited_from = time.monotonic()
    test = {role: SettleTest(noise_deg[role], block=block) for role in roles}
    while True:
        for role in roles:
            held = history[role]
            _gather(bench, role, held, start)
            if role not in passed and held:
                n = test[role].settled_after([channels(x) for x in held], checked[role])
                checked[role] = len(held)
                if n is not None:
                    passed[role] = held[n - 1].bench_s
                    blocks.append(test[role].block_at(n))
        if len(passed) == len(roles):
            return Settled(max(passed.values()), max(blocks))
        if _past_timeout(bench, history, start, timeout_s, waited_from):
            raise _not_settled(roles, passed, noise_deg, timeout_s)
        await bench.clock.sleep(_poll_interval_s(bench, roles))


async def probe_reading_noise(
    bench: BenchRuntime, roles: tuple[str, ...], n: int, *, after_bench_s: float, timeout_s: float
) -> dict[str, float]:
    """Each role's reading noise (deg, the larger of its channels) from its next `n` readings after
    `after_bench_s`: the standard deviation of successive differences over √2, which a transient
    still decaying slowly under the readings hardly touches (their plain spread would take it for
    noise). At least MIN_NOISE_DEG (a sensor whose quantised readings do not vary)."""
    got = await asyncio.gather(
        *(
            fresh_readings(bench, role, n, after_bench_s=after_bench_s, timeout_s=timeout_s)
            for role in roles
        )
    )
    return {
        role: noise_of_successive_differences([channels(x) for x in readings])
        for role, readings in zip(roles, got, strict=True)
    }


def noise_of_successive_differences(values: list[tuple[float, ...]]) -> float:
    """One reading's noise (the larger of the channels) from readings in time order: the standard
    deviation of their successive differences over √2, insensitive to a slow trend under them."""
    steps = np.diff(np.array(values, dtype=float), axis=0)
    return max(float(steps.std(axis=0, ddof=1).max()) / math.sqrt(2.0), MIN_NOISE_DEG)


def _not_settled(
    roles: tuple[str, ...], passed: dict[str, float], noise_deg: dict[str, float], timeout_s: float
) -> TimeoutError:
    """The error naming the roles still moving, beside the reading noise each was judged by."""
    moving = [role for role in roles if role not in passed]
    return TimeoutError(
        f"readings of {', '.join(moving)} did not settle within the reading noise "
        f"({', '.join(f'{noise_deg[role]:.2g} deg' for role in moving)}) in {timeout_s:g} s"
    )


def _past_timeout(
    bench: BenchRuntime,
    history: dict[str, list[Reading]],
    start: float,
    timeout_s: float,
    waited_from: float,
) -> bool:
    """Whether the wait is over: some role watched for `timeout_s` bench seconds since the start, or
    three times that in real time (at least 10 s) gone by while the bench clock lags.

    A role is watched while its readings come: a gap between two of them longer than
    STALL_INTERVALS output intervals counts as that many. A loaded machine running a sped-up
    simulation can stall for a real second, twenty bench seconds, in which the sensor's frames are
    lost, not sent late; the transient decays meanwhile, so the readings after the gap are
    settled, but counting the gap would time the wait out before the test has seen them."""
    watched = 0.0
    for role, held in history.items():
        longest_gap = STALL_INTERVALS * bench.output_interval_s(role)
        stamps = np.array([start, *(reading.bench_s for reading in held)])
        watched = max(watched, float(np.minimum(np.diff(stamps), longest_gap).sum()))
    return watched > timeout_s or time.monotonic() - waited_from > max(
        bench.clock.real_seconds(timeout_s) * 3, 10.0
    )
