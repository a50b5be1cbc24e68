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
    u = propagate(
        lambda p, x: x["d"] / p[0], np.array([m]), np.array([[u_m**2]]), {"d": np.array([d])}
    )
    assert u[0] == pytest.approx(d / m**2 * u_m, rel=1e-6)


@settings(max_examples=60, deadline=None)
@given(reading=st.floats(1e-9, 1e3), sigma_rel=st.floats(1e-6, 1e-2), gain=st.floats(0.1, 10.0))
def test_a_reading_noise_gets_the_analytic_sensitivity_in_any_unit(reading, sigma_rel, gain):
    # a square law in the reading: d(out)/d(reading) = 2 gain reading
    sigma = sigma_rel * reading
    u = propagate(
        lambda p, x: p[0] * x["r"] ** 2,
        np.array([gain]),
        None,
        {"r": np.array([reading])},
        input_sigma={"r": sigma},
    )
    assert u[0] == pytest.approx(2 * gain * reading * sigma, rel=1e-5)


def test_a_parameter_at_zero_is_stepped_by_a_fraction_of_its_uncertainty():
    u = propagate(
        lambda p, x: np.sin(p[0]) * x["k"],
        np.array([0.0]),
        np.array([[1e-6]]),
        {"k": np.array([3.0])},
    )
    assert u[0] == pytest.approx(3.0 * 1e-3, rel=1e-9)


# --- coverage factor from the effective degrees of freedom (JCGM 100 G.4)
# ----------------------------


def test_coverage_factor_is_students_t_at_the_degrees_of_freedom():
    from scipy import stats

    from service.calibration.uncertainty import coverage_factor

    for nu in (1, 2, 3.5, 5, 10, 30, 145, 1e6):
        assert float(coverage_factor(nu)) == pytest.approx(stats.t.ppf(0.975, nu), rel=1e-10)
    assert float(coverage_factor(np.inf)) == pytest.approx(stats.norm.ppf(0.975), rel=1e-12)
    assert float(coverage_factor(10, 0.99)) == pytest.approx(stats.t.ppf(0.995, 10), rel=1e-10)
    # seed 003 Table 1 has 10 degrees of freedom: k = 2 covers about 93 %, t(10) = 2.23 covers 95 %
    assert 2 * stats.t.cdf(2.0, 10) - 1 == pytest.approx(0.927, abs=0.001)
    assert 2 * stats.t.cdf(float(coverage_factor(10)), 10) - 1 == pytest.approx(0.95, abs=1e-9)


def test_welch_satterthwaite_by_hand():
    from service.calibration.uncertainty import welch_satterthwaite

    # two equal components with 5 and 10 degrees of freedom: 4 / (1/5 + 1/10)
    assert float(welch_satterthwaite([(np.array(1.0), 5), (np.array(1.0), 10)])) == pytest.approx(
        40 / 3
    )
    # a component known exactly (infinite dof) adds to u_c but not to the denominator
    assert float(
        welch_satterthwaite([(np.array(1.0), 4), (np.array(3.0), np.inf)])
    ) == pytest.approx(4 * 16)
    assert np.isinf(welch_satterthwaite([(np.array(2.0), np.inf)]))


def test_propagation_reports_the_effective_dof_of_its_components():
    from service.calibration.uncertainty import coverage_factor, propagate_gum

    # y = p + 2 x: parameter variance 0.09 (from a fit with 4 dof), reading sigma 0.2 (9 dof)
    g = propagate_gum(
        lambda p, x: p[0] + 2.0 * x["x"],
        np.array([1.0]),
        np.array([[0.09]]),
        {"x": np.array([0.5, 3.0])},
        {"x": 0.2},
        params_dof=4,
        inputs_dof=9,
    )
    var_p, var_x = 0.09, (2.0 * 0.2) ** 2
    nu = (var_p + var_x) ** 2 / (var_p**2 / 4 + var_x**2 / 9)
    assert np.allclose(g.u, np.sqrt(var_p + var_x))
    assert np.allclose(g.dof_eff, nu)
    assert np.allclose(g.expanded(), float(coverage_factor(nu)) * np.sqrt(var_p + var_x))


def test_seed003_table1_expanded_uncertainty_uses_its_ten_degrees_of_freedom():
    """A straight line through Table 1's 12 points: 10 degrees of freedom, k between t(10) and the
    normal 1.96."""
    from pathlib import Path

    from scipy import stats

    from service.calibration.registry import FitOptions, get_method
    from service.io.datasets import read_dataset

    table1 = (
        Path(__file__).resolve().parents[2]
        / "service"
        / "calibration"
        / "data"
        / "seed003_table1.csv"
    )
    m = get_method("scale", "poly1")
    ds = read_dataset(table1, "scale", m.fit_required, m.fit_optional)
    model = m.fit(ds.arrays(), FitOptions())
    assert model.fit["dof"] == 10
    reading = {"reading": np.array([500.0, 2000.0, 3500.0])}
    U = m.correct(model, reading)["u_angle_arcsec"]
    from tests.helpers.gum import Z95, without_dof

    u = m.correct(without_dof(model), reading)["u_angle_arcsec"] / Z95
    k = U / u
    assert np.all(k > 2.0) and np.all(k <= stats.t.ppf(0.975, 10) + 1e-12)


def test_coverage_factor_of_many_values_matches_students_t():
    """For thousands of readings at once k comes from a table in 1/ν: within 1e-7 of Student's t
    everywhere."""
    from scipy import stats

    from service.calibration.uncertainty import coverage_factor

    nu = np.exp(np.linspace(0.0, np.log(1e7), 5000))
    nu[-1] = np.inf
    k = coverage_factor(nu)
    assert np.allclose(k, stats.t.ppf(0.975, nu), rtol=1e-7, atol=0)
