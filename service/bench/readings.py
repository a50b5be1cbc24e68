"""Readings the daemon waits for (fresh ones after a move), their settling and their robust mean.

Outlier rule, stated once: a sample whose modified z-score |0.6745 (v - median) / MAD| exceeds
3.5 on any channel is rejected (Iglewicz and Hoaglin); the point's value is the mean of the rest.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from service.bench.runtime import BenchRuntime, DeviceNotAnswering
from service.instruments.base import Reading

OUTLIER_Z = 3.5
OUTLIER_RULE = "modified z-score |0.6745 (v - median) / MAD| > 3.5 on any channel rejects a sample"


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
    bench time (what the readings take to come), waited for in real time, and never less than 2 real
    seconds: a sped-up simulation on a loaded machine lags its bench clock."""
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


def robust_mean(readings: list[Reading]) -> Averaged:
    v = np.array([channels(r) for r in readings], dtype=float)
    med = np.median(v, axis=0)
    mad = np.median(np.abs(v - med), axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(mad > 0, 0.6745 * np.abs(v - med) / mad, 0.0)
    keep = ~(z > OUTLIER_Z).any(axis=1)
    kept = v[keep]
    temps = [r.temp_c for r, k in zip(readings, np.atleast_1d(keep)) if k and r.temp_c is not None]
    std = (
        tuple(float(s) for s in kept.std(axis=0, ddof=1)) if len(kept) > 1 else (None,) * v.shape[1]
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
) -> float:
    """Wait until every role's mean over the last `window_s` differs from its mean over the window
    before by at most `tolerance_deg` on every channel (a drift criterion: reading noise averages
    out).

    `timeout_s` is real seconds, whatever the simulation speed: a loaded machine running a sped-up
    simulation must not run out of it while its bench clock lags. Only readings made after the call
    count (`bench.sync`). Returns the bench time at which they settled; raises TimeoutError naming
    the roles that did not, DeviceNotAnswering (role and port) as soon as one of them is not
    connected.
    """
    # only readings made after the call count: a lagging reader may still hold some from the move
    start = await bench.sync(roles)
    waited_from = time.monotonic()
    history: dict[str, list[Reading]] = {r: [] for r in roles}
    while True:
        now = bench.clock.monotonic()
        moving = []
        for role in roles:
            # a sensor lost while waiting fails the wait at once, naming role and port
            bench.require(role)
            h = history[role]
            h += bench.readings_after(role, h[-1].bench_s if h else start)
            while h and h[0].bench_s < now - 2 * window_s:
                h.pop(0)
            if now - start < 2 * window_s:
                moving.append(role)
                continue
            older = [channels(x) for x in h if x.bench_s < now - window_s]
            newer = [channels(x) for x in h if x.bench_s >= now - window_s]
            if (
                not older
                or not newer
                or np.abs(np.mean(newer, axis=0) - np.mean(older, axis=0)).max() > tolerance_deg
            ):
                moving.append(role)
        if not moving:
            return now
        if time.monotonic() - waited_from > timeout_s:
            raise TimeoutError(
                f"readings of {', '.join(moving)} did not settle within {tolerance_deg:g} deg"
                f" between windows of {window_s:g} s in {timeout_s:g} s"
            )
        await bench.clock.sleep(min(bench.output_interval_s(r) for r in roles) / 2)


async def settle_statistical(
    bench: BenchRuntime, roles: tuple[str, ...], noise_deg: dict[str, float], *, timeout_s: float
) -> float:
    """Wait until every role's readings since the call pass the statistical settling test
    (service.bench.settled) against its reading noise `noise_deg[role]`; returns the bench time of
    the reading at which the last of them passed. `timeout_s` is bench time (a transient is bench
    physics); past it, TimeoutError names the roles still moving. DeviceNotAnswering as soon as one
    is not connected."""
    from service.bench.settled import SettleTest

    start = await bench.sync(roles)
    history: dict[str, list[Reading]] = {r: [] for r in roles}
    passed: dict[str, float] = {}
    checked = dict.fromkeys(roles, 0)
    waited_from = time.monotonic()
    while True:
        for role in roles:
            bench.require(role)
            h = history[role]
            h += bench.readings_after(role, h[-1].bench_s if h else start)
            if role not in passed and h:
                n = SettleTest(noise_deg[role]).settled_after(
                    [channels(x) for x in h], checked[role]
                )
                checked[role] = len(h)
                if n is not None:
                    passed[role] = h[n - 1].bench_s
        if len(passed) == len(roles):
            return max(passed.values())
        last = max((h[-1].bench_s for h in history.values() if h), default=start)
        if last - start > timeout_s or time.monotonic() - waited_from > max(
            bench.clock.real_seconds(timeout_s) * 3, 10.0
        ):
            moving = [r for r in roles if r not in passed]
            raise TimeoutError(
                f"readings of {', '.join(moving)} did not settle within the reading noise "
                f"({', '.join(f'{noise_deg[r]:.2g} deg' for r in moving)}) in {timeout_s:g} s"
            )
        await bench.clock.sleep(min(bench.output_interval_s(r) for r in roles) / 2)
