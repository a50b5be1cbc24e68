"""The Type A uncertainty of a mean of readings (`mean_type_a`), checked against simulated truth:
white noise and an AR(1) series (readings correlated as a filtered or slowly wandering sensor's
are), each over many series of several lengths. The stated 95 % interval must cover the true mean
about 95 % of the time; for correlated readings s/√n alone would cover far less, which the same
series show."""

from __future__ import annotations

import numpy as np
import pytest

from service.calibration.uncertainty import coverage_factor, mean_type_a

SERIES = 2000


def _ar1(rng: np.random.Generator, n: int, rho: float) -> np.ndarray:
    e = rng.normal(0.0, 1.0, n)
    x = np.empty(n)
    x[0] = e[0] / np.sqrt(1 - rho**2)
    for i in range(1, n):
        x[i] = rho * x[i - 1] + e[i]
    return x


@pytest.mark.parametrize(("rho", "n"), [(0.0, 10), (0.0, 100), (0.5, 200), (0.8, 400)])
def test_the_mean_s_interval_covers_the_true_mean(rho, n):
    rng = np.random.default_rng(1000 + int(rho * 10) + n)
    hits = naive_hits = 0
    for _ in range(SERIES):
        x = 5.0 + _ar1(rng, n, rho)
        m = mean_type_a(x)
        U = float(coverage_factor(m.dof)) * m.u
        hits += abs(m.mean - 5.0) <= U
        naive_hits += abs(m.mean - 5.0) <= float(coverage_factor(n - 1)) * np.std(
            x, ddof=1
        ) / np.sqrt(n)
    coverage, naive = hits / SERIES, naive_hits / SERIES
    assert 0.92 <= coverage <= 0.98, (rho, n, coverage)
    if rho >= 0.5:
        assert naive < 0.85, naive  # what ignoring the correlation would have stated


def test_the_readings_are_worth_fewer_when_correlated_and_two_are_needed():
    rng = np.random.default_rng(7)
    white, wander = mean_type_a(rng.normal(size=400)), mean_type_a(_ar1(rng, 400, 0.8))
    assert white.n_eff > 300 and wander.n_eff < 80
    assert wander.lag1 == pytest.approx(0.8, abs=0.1)
    with pytest.raises(ValueError, match="two readings"):
        mean_type_a([1.0])
