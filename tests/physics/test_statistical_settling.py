"""The statistical settling test ends as soon as what is left of the transient is within the reading
noise: within a stated number of time constants on a bench with settling, after three blocks
without."""

from __future__ import annotations

import numpy as np
import pytest

from service.bench.readings import MIN_NOISE_DEG, noise_of_successive_differences
from service.bench.settled import BLOCK, SettleTest
from service.physics.settling import Move, Settling, move_transient_deg

RATE_HZ = 25.0  # the simulated sensors' default output rate
SIGMA = 0.001  # reading noise of the seed 000 sensors, deg


def _step(
    st: Settling, seed: int, delta: float = 3.0, duration: float = 1.07, span_s: float = 20.0
):
    t = np.arange(0.0, span_s, 1.0 / RATE_HZ)
    move = Move(-duration, delta, duration)
    rng = np.random.default_rng(seed)
    truth = move_transient_deg(st, move, t)
    return t, truth, truth + rng.normal(0.0, SIGMA, t.size)


@pytest.mark.parametrize("tau", [0.1, 0.3, 1.0, 3.0])
@pytest.mark.parametrize("seed", range(4))
def test_ends_within_the_stated_time_constants_and_leaves_less_than_the_noise(tau, seed):
    """Stated bound: it ends within 1.4 x the time the transient takes to stay below the reading
    noise, plus
    0.5 s (three blocks, and blocks that grow with the wait). For a lag-dominated step that time is
    tau ln(lag / sigma): about 7 time constants for a 3 deg move read with 0.001 deg of noise."""
    st = Settling(tau, 0.002, 4.0, 0.5)
    t, truth, read = _step(st, seed, span_s=max(20.0, 15 * tau))
    n = SettleTest(SIGMA).settled_after(read)
    assert n is not None
    t_end = t[n - 1]
    above = np.nonzero(np.abs(truth) >= SIGMA)[0]
    t_below = t[above[-1] + 1]  # from here on the transient stays within the noise
    assert t_end <= 1.4 * t_below + 0.5, (t_end, t_below)
    if tau >= 0.3:  # the lag dominates: the bound in time constants
        assert t_end <= 1.4 * tau * np.log(abs(truth[0]) / SIGMA) + 0.5
    # it does not end early: what is left of the transient when it ends, and after, is within the
    # noise
    assert np.all(np.abs(truth[n - 1 :]) < SIGMA)


@pytest.mark.parametrize("seed", range(10))
def test_a_bench_without_settling_ends_at_once(seed):
    t, truth, read = _step(Settling(), seed)
    n = SettleTest(SIGMA).settled_after(read)
    # three blocks, a few more readings when the noise says so
    assert n is not None and n <= 3 * BLOCK + 8


@pytest.mark.parametrize("seed", range(4))
def test_noise_probed_under_a_slow_transient_is_the_reading_noise(seed):
    """A point that has no reading noise yet probes it from 20 readings taken while a 1.5 s
    transient still decays under them (20 x the noise left, 8 x the noise of it gone within the 20
    readings): their successive differences give the noise (within 0.5-1.7 of it: the 0.1 and 99.9
    percentiles of 2,000 draws are 0.50 and 1.62), where their plain spread takes the trend for
    noise (at least 1.98 x it in the same draws)."""
    t, truth, read = _step(Settling(sensor_time_constant_s=1.5), seed, span_s=40.0)
    start = int(np.argmax(np.abs(truth) < 20 * SIGMA))
    values = read[start : start + 20]
    probed = noise_of_successive_differences([(float(v),) for v in values])
    assert 0.5 * SIGMA < probed < 1.7 * SIGMA, probed
    assert np.std(values, ddof=1) > 1.9 * SIGMA
    assert noise_of_successive_differences([(1.0,)] * 20) == MIN_NOISE_DEG


@pytest.mark.parametrize("seed", range(6))
def test_a_slow_sensors_small_transient_needs_the_blocks_its_large_one_passed_with(seed):
    """After a short move (0.02 deg) a 1.5 s sensor's transient is small: blocks of 4 readings
    (0.16 s) cannot see it decay and pass while some 4 x the noise is left. A job raises the
    shortest block to half the block the test passed with after a large move (8 deg, where the
    blocks had grown with the wait), and the small transient then passes within the noise. Over
    1,000 draws: short blocks left at least 2.3 x the noise in a point's 30 readings, the raised
    ones at most 0.81 x the noise when passing and 0.55 x it in the point."""
    st = Settling(1.5, 0.002, 2.5, 1.0)
    t_big, truth_big, read_big = _step(st, 100 + seed, delta=8.0, duration=0.8, span_s=40.0)
    test = SettleTest(SIGMA)
    learnt = test.block_at(test.settled_after(read_big) or 0) // 2
    assert learnt > 2 * BLOCK
    t, truth, read = _step(st, seed, delta=0.02, duration=0.002, span_s=40.0)
    short = SettleTest(SIGMA).settled_after(read)
    floored = SettleTest(SIGMA, block=learnt).settled_after(read)
    assert short is not None and floored is not None
    # what is left when each passes, and over the 30 readings a point then takes
    assert np.abs(truth[short : short + 30]).mean() > 2 * SIGMA
    assert np.all(np.abs(truth[floored - 1 :]) < SIGMA)
    assert np.abs(truth[floored : floored + 30]).mean() < 0.75 * SIGMA
