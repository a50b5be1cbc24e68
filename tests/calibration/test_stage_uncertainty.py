"""GUM (JCGM 100) uncertainty of corrected tilts against a Monte Carlo propagation (JCGM 101)."""

import numpy as np
import pytest

from service.calibration.methods.stage.base import reading_noise_of
from service.calibration.methods.stage.common import MEAS_NAMES, meas_inverse
from service.calibration.projective import apply_projective
from service.calibration.registry import FitOptions, get_method
from service.reproduce.stage_validation import Oracle, execute, paper_grid
from service.scenarios import load_scenario, run_scenario
from tests.helpers.gum import Z95, without_dof

N_MC = 4000


def _mc_std(model, names, tilt_of, meas_x, meas_y, rng):
    """Standard deviation of the corrected tilt when parameters and readings are drawn from their
    distributions."""
    p = model.values(names)
    cov = model.cov_of(names)
    sigma, noise_dof = reading_noise_of(model)  # one reading's noise and its degrees of freedom
    draws = rng.multivariate_normal(p, cov, size=N_MC, method="eigh")
    out = np.empty((N_MC, 2, meas_x.size))
    for i, q in enumerate(draws):
        a = meas_x + rng.normal(0.0, sigma, meas_x.size)
        b = meas_y + rng.normal(0.0, sigma, meas_y.size)
        out[i] = tilt_of(q, a, b)
    return out.std(axis=0, ddof=1)


def _readings(seed):
    sc = load_scenario("seed000")
    run = run_scenario(sc, seed=seed)
    tx, ty = paper_grid()
    pick = np.arange(0, tx.size, 4)  # 21 points over the grid
    oracle = Oracle(run.bench, run.effects, sc.environment.temp_c)
    cx, cy = oracle.level(tx[pick], ty[pick])
    val = execute(run.bench, run.effects, cx, cy, 90_000 + seed, sc.environment.temp_c)
    return run, val


@pytest.mark.parametrize("seed", [201, 202])
def test_kinematic_gum_matches_monte_carlo(seed):
    run, val = _readings(seed)
    m = get_method("stage", "kinematic")
    model = m.fit(run.columns, FitOptions())
    readings = {"meas_x_deg": val["meas_x_deg"], "meas_y_deg": val["meas_y_deg"]}
    out = m.correct(model, readings)
    std = m.correct(without_dof(model), readings)
    # back to standard uncertainty
    u_gum = np.stack([std["u_tilt_x_deg"], std["u_tilt_y_deg"]]) / Z95
    sign = np.asarray(model.state["meas_sign"])

    def tilt_of(q, a, b):
        return np.stack(meas_inverse(q, sign, a, b))

    u_mc = _mc_std(
        model,
        list(MEAS_NAMES),
        tilt_of,
        val["meas_x_deg"],
        val["meas_y_deg"],
        np.random.default_rng(seed),
    )
    # MC standard deviation from 4000 draws is good to ~1.1 % (1 sigma)
    assert np.max(np.abs(u_mc / u_gum - 1.0)) < 0.06
    # whether U covers the truth is tests/calibration/test_coverage.py's, pooled over realisations:
    # one realisation's 42 errors share its parameter error and its estimate of the reading noise
    assert np.all(np.isfinite(out["u_tilt_x_deg"])) and np.all(out["u_tilt_y_deg"] > 0)


def test_homography_gum_matches_monte_carlo():
    run, val = _readings(203)
    m = get_method("stage", "homography")
    model = m.fit(run.columns, FitOptions())
    out = m.correct(
        without_dof(model), {"meas_x_deg": val["meas_x_deg"], "meas_y_deg": val["meas_y_deg"]}
    )
    u_gum = np.stack([out["u_tilt_x_deg"], out["u_tilt_y_deg"]]) / Z95
    names = [f"H2.{k}" for k in ("h11", "h12", "h13", "h21", "h22", "h23", "h31", "h32")]

    def tilt_of(q, a, b):
        return np.stack(apply_projective(np.append(q, 1.0).reshape(3, 3), a, b))

    u_mc = _mc_std(
        model, names, tilt_of, val["meas_x_deg"], val["meas_y_deg"], np.random.default_rng(7)
    )
    assert np.max(np.abs(u_mc / u_gum - 1.0)) < 0.06


def test_kinematic_fast_gum_equals_the_generic_propagation():
    """correct's specialised propagation (zero/scale sensitivities from the reading's) =
    uncertainty.propagate_gum, degrees of freedom and coverage factors included."""
    from service.calibration.uncertainty import propagate_gum

    cols = run_scenario(load_scenario("seed000"), seed=204).columns
    m = get_method("stage", "kinematic")
    model = m.fit(cols, FitOptions())
    out = m.correct(model, cols)
    sign = np.asarray(model.state["meas_sign"])
    sigma, noise_dof = reading_noise_of(model)  # one reading's noise and its degrees of freedom

    def f(p, inp):
        return np.column_stack(meas_inverse(p, sign, inp["meas_x_deg"], inp["meas_y_deg"]))

    dof = model.state["meas_dof"]  # the parameters' covariance's
    g = propagate_gum(
        f,
        model.values(MEAS_NAMES),
        model.cov_of(list(MEAS_NAMES)),
        {k: cols[k] for k in ("meas_x_deg", "meas_y_deg")},
        {"meas_x_deg": sigma, "meas_y_deg": sigma},
        dof,
        noise_dof,
    )
    U = g.expanded()
    assert np.allclose(out["u_tilt_x_deg"], U[:, 0], rtol=1e-6, atol=0)
    assert np.allclose(out["u_tilt_y_deg"], U[:, 1], rtol=1e-6, atol=0)
    # Welch-Satterthwaite: the effective degrees of freedom are at least the fewest of the parts'
    # (the reading noise's from its three-way estimate, the parameters' from the fit), and k is
    # Student's t at them
    from scipy.stats import t as student_t

    assert np.all(g.dof_eff >= min(dof, noise_dof) - 1e-9), (g.dof_eff.min(), dof, noise_dof)
    assert np.allclose(U / g.u, student_t.ppf(0.975, g.dof_eff), rtol=1e-6)


def _seed000(**grid):
    from service.scenarios import parse_scenario

    data = load_scenario("seed000").model_dump(mode="json", exclude_defaults=True)
    data["grid"].update(grid)
    return parse_scenario(data)


@pytest.mark.parametrize("method", ["homography", "axis-transform", "kinematic"])
def test_reading_noise_is_the_measurement_sensors_alone_when_the_data_say_the_references(method):
    """The meas-vs-ref residual holds both sensors' noise; with readings repeated at each stand (or
    the reference's noise stated) the reading term of a corrected tilt is the measurement sensor's,
    not the residual."""
    m = get_method("stage", method)
    sigmas, three_way = [], []
    for seed in (301, 302, 303):
        run = run_scenario(_seed000(readings_per_stand=3), seed=seed)
        model = m.fit(run.columns, FitOptions())
        st = model.state
        assert "repeated readings" in st["meas_reading_noise_source"]
        sigmas.append(
            (
                st["meas_reading_standard_uncertainty_deg"],
                st["ref_reading_standard_uncertainty_deg"],
                st["meas_sigma_deg"],
            )
        )
        # the same data with the reference's noise stated instead of repeated
        single = {k: v[::3] for k, v in run.columns.items() if k != "point"}
        stated = m.fit(single, FitOptions(extra={"ref_noise_deg": 0.001})).state
        assert "stated noise" in stated["meas_reading_noise_source"]
        plain = m.fit(single, FitOptions()).state
        # the stage model's prediction is the third instrument (the axis transform's own misses by
        # tenths of a degree: a projective map of the stage stands in for it)
        assert "three-way" in plain["meas_reading_noise_source"]
        three_way.append(plain["meas_reading_standard_uncertainty_deg"])
        if method == "axis-transform":
            # taken about the bias its model leaves (no zero offsets), which dominates its
            # residual's rms
            assert plain["meas_reading_standard_uncertainty_deg"] < 0.1 * plain["meas_sigma_deg"]
            assert np.all(np.abs(plain["meas_uncorrected_bias_deg"]) > 0.03)
    s = np.array(sigmas)
    # the model describes the bench: what is left is the measurement sensor's noise
    if method == "kinematic":
        # the measurement sensor's sigma 0.001 deg
        assert np.all(np.abs(s[:, 0] / 0.001 - 1) < 0.15), s
        assert np.all(s[:, 2] > 1.3 * s[:, 0])  # the residual holds both (√2 for two equal sensors)
    # a misfit of the model (H2's projective map; what varies along the range of the axis
    # transform's, whose bias is kept apart) stays in the reading term
    else:
        assert np.all((s[:, 0] > 0.00085) & (s[:, 0] < s[:, 2])), s
    assert np.all(np.abs(s[:, 1] / 0.001 - 1) < 0.15), s  # the reference's, from the repeats
    if method == "kinematic":
        # one reading a stand, nothing stated: the three-way estimate is the measurement sensor's
        # noise too (each to about 16 %: the mean of three within 25 %), below the residual
        assert abs(np.mean(three_way) / 0.001 - 1) < 0.25, three_way
    elif method == "axis-transform":
        # the same with what the model leaves along the range in it (y: about 0.001 deg), as
        # with the reference's noise known from repeats
        assert np.all((np.array(three_way) > 0.00085) & (np.array(three_way) < 0.0025)), three_way
    if three_way:
        assert np.all(np.array(three_way) < s[:, 2]), (three_way, s)
