"""The interval for a result that keeps a known bias, against scipy's folded normal (an independent
implementation) and against draws."""

import numpy as np
import pytest
from scipy import stats

from service.calibration.uncertainty import bias_interval


@pytest.mark.parametrize(("bias", "u"), [(0.0, 1.0), (0.5, 1.0), (3.0, 1.0), (-0.049, 0.0013)])
def test_bias_interval_is_the_folded_normals_95_percent_point(bias, u):
    expected = stats.foldnorm.ppf(0.95, abs(bias) / u, scale=u)
    assert bias_interval(bias, u) == pytest.approx(expected, rel=1e-9)


def test_bias_interval_holds_95_percent_of_draws_and_is_vectorised():
    rng = np.random.default_rng(7)
    bias, u = np.array([0.0, 0.02, -0.05]), np.array([0.01, 0.01, 0.002])
    half_width = bias_interval(bias, u)
    draws = bias + u * rng.standard_normal((200_000, 3))
    held = np.mean(np.abs(draws) <= half_width, axis=0)
    assert np.all(np.abs(held - 0.95) < 0.003), held
    # without a bias it is the normal's 1.96 u; with a large one, |b| + 1.645 u
    assert half_width[0] == pytest.approx(1.959964 * 0.01, rel=1e-6)
    assert half_width[2] == pytest.approx(0.05 + 1.644854 * 0.002, rel=1e-4)
