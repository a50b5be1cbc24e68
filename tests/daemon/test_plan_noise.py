"""The noise an adaptive plan starts from is each axis's own, estimated without bias: over many
first points drawn from a known truth (20 readings of each sensor), the mean of the plan's variance
of meas − ref on each axis is the true one to within 1 %. Each sensor's noisier axis taken for both
overstates it (by some 18 % where the axes are alike), and the plan then read that much more than
the target needed."""

from __future__ import annotations

import numpy as np
import pytest

from service.bench.readings import MIN_NOISE_DEG
from service.calibration.adaptive_design import NOISE_READINGS
from service.jobs.adaptive import _axis_variances, _noise_of

DEVICES = {"reference_sensor": 1, "measurement_sensor": 2}


def _first_points(sigma_deg: dict[int, tuple[float, float]], n: int) -> list[dict[int, dict]]:
    """`n` first points: each sensor's spread of its 20 readings on x and y, drawn from one
    reading's noise `sigma_deg` (per device, x and y)."""
    rng = np.random.default_rng()
    out = []
    for _ in range(n):
        settled = {}
        for device, sigma in sigma_deg.items():
            x, y = rng.normal(0.0, sigma, (NOISE_READINGS, 2)).T
            settled[device] = {"ch_x_std": float(x.std(ddof=1)), "ch_y_std": float(y.std(ddof=1))}
        out.append(settled)
    return out


def test_the_plans_noise_is_each_axis_own_and_unbiased():
    # the reference's y axis noisier than its x
    sigma_deg = {1: (1.0e-3, 1.5e-3), 2: (1.2e-3, 1.1e-3)}
    true = [sum(sigma[axis] ** 2 for sigma in sigma_deg.values()) for axis in (0, 1)]
    planned = np.array(
        [_axis_variances(settled, DEVICES) for settled in _first_points(sigma_deg, 20_000)]
    )
    # 20,000 draws of a variance on about 38 degrees of freedom: standard error of the mean 0.2 %
    assert planned.mean(axis=0) == pytest.approx(true, rel=0.01)


def test_the_noisier_axis_for_both_would_overstate_alike_axes():
    sigma_deg = {1: (1.0e-3, 1.0e-3), 2: (1.0e-3, 1.0e-3)}
    draws = _first_points(sigma_deg, 20_000)
    noisier = np.mean(
        [sum(v**2 for v in _noise_of(settled, DEVICES).values()) for settled in draws]
    )
    planned = np.mean([_axis_variances(settled, DEVICES) for settled in draws])
    assert planned == pytest.approx(2e-6, rel=0.01)
    assert noisier == pytest.approx(1.18 * 2e-6, rel=0.02)


def test_a_sensor_whose_readings_do_not_vary_counts_its_floor():
    quiet = {device: {"ch_x_std": 0.0, "ch_y_std": None} for device in (1, 2)}
    assert _axis_variances(quiet, DEVICES) == (2 * MIN_NOISE_DEG**2, 2 * MIN_NOISE_DEG**2)
