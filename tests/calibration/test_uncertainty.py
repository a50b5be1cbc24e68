"""GUM propagation: sensitivities are right whatever the unit a parameter or reading is in."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.calibration.uncertainty import propagate


@settings(max_examples=60, deadline=None)
@given(scale=st.floats(1e-9, 1e6), rel_u=st.floats(1e-6, 1e-2), d=st.floats(0.1, 100.0))
def test_a_quotient_gets_its_analytic_uncertainty_in_any_unit(scale, rel_u, d):
    # angle = half-difference / scale factor, as the turntable's compensation: u = d/m^2 * u_m
    m, u_m = scale, rel_u * scale
    u = propagate(lambda p, x: x["d"] / p[0], np.array([m]), np.array([[u_m**2]]), {"d": np.array([d])})
    assert u[0] == pytest.approx(d / m**2 * u_m, rel=1e-6)


@settings(max_examples=60, deadline=None)
@given(reading=st.floats(1e-9, 1e3), sigma_rel=st.floats(1e-6, 1e-2), gain=st.floats(0.1, 10.0))
def test_a_reading_noise_gets_the_analytic_sensitivity_in_any_unit(reading, sigma_rel, gain):
    # a square law in the reading: d(out)/d(reading) = 2 gain reading
    sigma = sigma_rel * reading
    u = propagate(lambda p, x: p[0] * x["r"] ** 2, np.array([gain]), None, {"r": np.array([reading])},
                  input_sigma={"r": sigma})
    assert u[0] == pytest.approx(2 * gain * reading * sigma, rel=1e-5)


def test_a_parameter_at_zero_is_stepped_by_a_fraction_of_its_uncertainty():
    u = propagate(lambda p, x: np.sin(p[0]) * x["k"], np.array([0.0]), np.array([[1e-6]]), {"k": np.array([3.0])})
    assert u[0] == pytest.approx(3.0 * 1e-3, rel=1e-9)
