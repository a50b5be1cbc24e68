"""Seed 004 reversal method: recovery, the β-φ sensitivity, refusals, uncertainty, CLI."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import service.calibration.methods.turntable as mt
from service.calibration.model import CalibrationModel
from service.calibration.registry import FitOptions, get_method
from service.errors import DegenerateDataError
from service.physics.effects import EffectSet
from service.physics.turntable import TurntableInclinometer, simulate_turntable
from service.scenarios import load_scenario, run_scenario
from service.scenarios.model import parse_scenario
from tests.helpers.gum import Z95, without_dof

PARAMS = ["beta_deg", "m1_per_arcsec", "m2_per_arcsec", "epsilon_deg"]
REVERSAL = get_method("turntable", "reversal")


def _pairs(beta, eps, m1, m2, azimuths, tilts, rotation_deg=180.0, z=(0.0, 0.0)):
    """Noise-free pairs from the physics module (docs/models.md §4), one row per (azimuth, tilt)."""
    p = TurntableInclinometer(beta, eps, m1, m2)
    az = np.tile(np.asarray(azimuths, dtype=float), len(tilts))
    xi = np.repeat([t[0] for t in tilts], len(azimuths))
    eta = np.repeat([t[1] for t in tilts], len(azimuths))
    fx = EffectSet.from_mapping("turntable", {"zero_offset": {"z1": z[0], "z2": z[1]}})
    cols = simulate_turntable(p, fx, az, xi, eta, rotation_deg=rotation_deg)
    return {k: cols[k] for k in REVERSAL.fit_required}


def _seed004_columns(seed=0, **bench):
    data = load_scenario("seed004").model_dump()
    data["bench"].update(bench)
    return run_scenario(parse_scenario(data), seed=seed)


# --- recovery ------------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    st.floats(-179, 179),
    st.floats(-2, 2),
    st.floats(0.001, 0.01),
    st.floats(0.001, 0.01),
    st.floats(170, 190),
)
def test_noiseless_pairs_give_back_beta_m1_m2_epsilon(beta, eps, m1, m2, phi):
    """With the assumed φ equal to the true one the iterated least squares lands on the truth."""
    tilts = [(40.0, 10.0), (-25.0, 35.0), (5.0, -45.0)]
    cols = _pairs(beta, eps, m1, m2, [0, 45, 90, 135], tilts, rotation_deg=phi, z=(0.05, -0.03))
    model = REVERSAL.fit(cols, FitOptions(rotation_deg=phi))
    got = model.values(PARAMS)
    assert abs((got[0] - beta + 180) % 360 - 180) < 1e-7 and abs(got[3] - eps) < 1e-7
    assert got[1] == pytest.approx(m1, rel=1e-9) and got[2] == pytest.approx(m2, rel=1e-9)
    out = REVERSAL.correct(model, cols)
    assert np.allclose(out["north_arcsec"], cols["ref_north_arcsec"], atol=1e-7)
    assert np.allclose(out["east_arcsec"], cols["ref_east_arcsec"], atol=1e-7)


def test_the_papers_iteration_from_rough_initial_values_reaches_the_same_answer():
    run = _seed004_columns(seed=1)
    linear_start = REVERSAL.fit(run.columns, FitOptions())
    rough = {"beta_deg": 0.0, "m1_per_arcsec": 0.005, "m2_per_arcsec": 0.005, "epsilon_deg": 0.0}
    paper_start = REVERSAL.fit(run.columns, FitOptions(extra={"initial": rough}))
    assert paper_start.fit["iterations"] > linear_start.fit["iterations"]
    assert np.allclose(
        paper_start.values(PARAMS), linear_start.values(PARAMS), rtol=1e-8, atol=1e-8
    )


def test_seed004_bench_is_recovered_within_its_uncertainty():
    """Across seeds the estimates scatter around the truth as their standard uncertainties say."""
    truth = np.array([32.5, 0.004858, 0.004838, 0.15])
    z = []
    for seed in range(40):
        model = REVERSAL.fit(
            run_scenario(load_scenario("seed004"), seed=seed).columns, FitOptions()
        )
        z.append((model.values(PARAMS) - truth) / np.sqrt(np.diag(model.covariance)))
    z = np.array(z)
    assert np.all(np.abs(z.mean(axis=0)) < 0.5) and np.all(
        (z.std(axis=0) > 0.7) & (z.std(axis=0) < 1.3)
    ), z.std(axis=0)


# --- seed 004 §3.2: β and φ ----------------------------------------------------------------------


def test_a_rotation_error_of_one_degree_moves_beta_by_half_a_degree():
    run = _seed004_columns(seed=3, rotation_deg=181.0)  # the turntable really turns 181°
    at180 = REVERSAL.fit(run.columns, FitOptions(rotation_deg=180.0))
    at181 = REVERSAL.fit(run.columns, FitOptions(rotation_deg=181.0))
    assert at180.value("beta_deg") - at181.value("beta_deg") == pytest.approx(0.5, abs=1e-9)
    assert abs(at181.value("beta_deg") - 32.5) < 3 * at181.std("beta_deg")
    assert abs(at180.value("beta_deg") - 33.0) < 3 * at180.std("beta_deg")


def test_beta_follows_the_assumed_rotation_at_minus_half_and_the_residuals_cannot_tell():
    run = _seed004_columns(seed=4)
    phis = np.arange(176.0, 184.5, 0.5)
    fits = [REVERSAL.fit(run.columns, FitOptions(rotation_deg=float(p))) for p in phis]
    beta = np.array([f.value("beta_deg") for f in fits])
    assert np.polyfit(phis, beta, 1)[0] == pytest.approx(-0.5, abs=1e-9)
    rms = np.array([f.residuals["columns"]["north_arcsec"]["rms"] for f in fits])
    assert np.ptp(rms) < 1e-9 * rms.mean()  # identical fits: φ is not identifiable
    m1 = np.array([f.value("m1_per_arcsec") for f in fits])
    # symmetric about 180°
    assert np.allclose(m1, m1[len(phis) // 2] / np.cos(np.radians(phis - 180.0) / 2), rtol=1e-9)
    eps = np.array([f.value("epsilon_deg") for f in fits])
    assert np.ptp(eps) < 1e-9
    assert any("cannot be told apart" in n for n in fits[0].notes)
    assert (
        fits[0].parameters["rotation_deg"].fixed and "rotation_deg" not in fits[0].covariance_names
    )


def test_pairs_turned_the_other_way_give_the_same_instrument():
    """φ = -180° (the turntable turned back) is the same pair geometry as +180°: same β, m1, m2,
    ε."""
    tilts = [(40.0, 10.0), (-25.0, 35.0), (5.0, -45.0)]
    cols = _pairs(12.0, 0.3, 0.005, 0.0052, [0, 45, 90, 135], tilts, rotation_deg=-180.0)
    model = REVERSAL.fit(cols, FitOptions(rotation_deg=-180.0))
    got = model.values(PARAMS)
    assert got[0] == pytest.approx(12.0, abs=1e-7) and got[3] == pytest.approx(0.3, abs=1e-7)
    assert got[1] == pytest.approx(0.005, rel=1e-9) and got[2] == pytest.approx(0.0052, rel=1e-9)


# --- refusals -----------------------------------------------------------------------------------


def test_pairs_that_cannot_separate_the_parameters_are_refused():
    kw = dict(beta=30.0, eps=0.1, m1=0.005, m2=0.005)
    one_az_one_tilt = _pairs(azimuths=[45.0] * 6, tilts=[(30.0, 10.0)], **kw)
    with pytest.raises(
        DegenerateDataError,
        match=r"single direction.*1 distinct azimuth.*1 distinct reference tilt",
    ):
        REVERSAL.fit(one_az_one_tilt, FitOptions())
    # 180° apart: the same direction
    opposite = _pairs(azimuths=[20.0, 200.0, 20.0], tilts=[(30.0, 10.0)], **kw)
    with pytest.raises(DegenerateDataError, match="another azimuth"):
        REVERSAL.fit(opposite, FitOptions())
    plumb = _pairs(azimuths=[0, 45, 90, 135], tilts=[(0.0, 0.0)], **kw)
    with pytest.raises(DegenerateDataError, match="reference tilt.*zero"):
        REVERSAL.fit(plumb, FitOptions())
    two = _pairs(azimuths=[0, 90], tilts=[(30.0, 10.0)], **kw)
    with pytest.raises(DegenerateDataError, match="at least 3 pairs"):
        REVERSAL.fit(two, FitOptions())


def test_one_azimuth_with_tilts_in_several_directions_is_enough():
    """What separates β from m is the tilt direction seen by the instrument, so several levellings
    read at a single azimuth determine the parameters as well as several azimuths at one levelling
    do."""
    kw = dict(beta=30.0, eps=0.1, m1=0.005, m2=0.004)
    for cols in (
        _pairs(azimuths=[45.0] * 2, tilts=[(30.0, 10.0), (-5.0, 40.0)], **kw),
        _pairs(azimuths=[0.0, 60.0, 100.0], tilts=[(30.0, 10.0)], **kw),
    ):
        model = REVERSAL.fit(cols, FitOptions())
        assert np.allclose(model.values(PARAMS), [30.0, 0.005, 0.004, 0.1], rtol=1e-8, atol=1e-8)


def test_a_fit_that_does_not_converge_is_refused(monkeypatch):
    run = _seed004_columns(seed=2)
    monkeypatch.setattr(mt, "MAX_ITERATIONS", 2)
    rough = {"beta_deg": -100.0, "m1_per_arcsec": 0.02, "m2_per_arcsec": 0.001, "epsilon_deg": 3.0}
    with pytest.raises(DegenerateDataError, match="did not converge"):
        REVERSAL.fit(run.columns, FitOptions(extra={"initial": rough}))


# --- MODEL.json, CLI ------------------------------------------------------------------------------


def test_model_round_trips_through_json():
    run = _seed004_columns(seed=5)
    model = REVERSAL.fit(run.columns, FitOptions(rotation_deg=181.5))
    back = CalibrationModel.from_json_dict(
        json.loads(json.dumps(model.to_json_dict(), allow_nan=False))
    )
    assert back.value("rotation_deg") == 181.5
    a, b = REVERSAL.correct(model, run.columns), REVERSAL.correct(back, run.columns)
    assert set(a) == {
        "north_arcsec",
        "east_arcsec",
        "u_north_arcsec",
        "u_east_arcsec",
        "k_north",
        "k_east",
    }
    for k in a:
        assert np.array_equal(a[k], b[k])


def _tiltlab(*args, cwd):
    return subprocess.run(
        [sys.executable, "-m", "service", *args], cwd=cwd, capture_output=True, text=True
    )


def test_cli_round_trip_with_the_assumed_rotation(tmp_path):
    from service.io.datasets import write_dataset

    write_dataset(tmp_path / "run.csv", run_scenario(load_scenario("seed004")).columns)
    r = _tiltlab(
        "calibrate",
        "--kind",
        "turntable",
        "--method",
        "reversal",
        "--input",
        "run.csv",
        "--out",
        "m.json",
        "--rotation-deg",
        "179",
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "m.json").read_text())
    assert doc["parameters"]["rotation_deg"] == {
        "value": 179.0,
        "unit": "deg",
        "fixed": True,
        "note": doc["parameters"]["rotation_deg"]["note"],
    }
    assert doc["parameters"]["beta_deg"]["value"] == pytest.approx(33.0, abs=0.4)
    (tmp_path / "pairs.csv").write_text(
        "azimuth_deg,n1_a,n2_a,n1_b,n2_b\n0,0.24,-0.093,-0.14,0.034\n"
    )
    r = _tiltlab(
        "correct", "--model", "m.json", "--input", "pairs.csv", "--out", "out.csv", cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr
    header, row = (tmp_path / "out.csv").read_text().strip().splitlines()
    cells = dict(zip(header.split(","), row.split(",")))
    assert header.split(",")[5:] == [
        "north_arcsec",
        "expanded_uncertainty_north_arcsec",
        "standard_uncertainty_north_arcsec",
        "coverage_factor_north",
        "east_arcsec",
        "expanded_uncertainty_east_arcsec",
        "standard_uncertainty_east_arcsec",
        "coverage_factor_east",
        "coverage_probability",
    ]
    north, east, un, ue = (
        float(cells[c])
        for c in (
            "north_arcsec",
            "east_arcsec",
            "expanded_uncertainty_north_arcsec",
            "expanded_uncertainty_east_arcsec",
        )
    )
    assert 35 < north < 45 and 5 < east < 15 and 0 < un < 2 and 0 < ue < 2


def test_cli_refuses_a_single_direction_with_exit_2(tmp_path):
    rows = ["azimuth_deg,n1_a,n2_a,n1_b,n2_b,ref_north_arcsec,ref_east_arcsec"]
    rows += ["30,0.2,0.1,-0.1,-0.05,40,10"] * 5
    (tmp_path / "one.csv").write_text("\n".join(rows) + "\n")
    r = _tiltlab(
        "calibrate",
        "--kind",
        "turntable",
        "--method",
        "reversal",
        "--input",
        "one.csv",
        "--out",
        "m.json",
        cwd=tmp_path,
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "azimuth" in r.stderr


# --- uncertainty ---------------------------------------------------------------------------------


def test_gum_uncertainty_of_the_compensation_matches_monte_carlo():
    for seed in (1, 2, 3):
        run = run_scenario(load_scenario("seed004"), seed=seed)
        model = REVERSAL.fit(run.columns, FitOptions())
        meas = {c: run.columns[c][:8] for c in REVERSAL.correct_required}
        out = REVERSAL.correct(without_dof(model), meas)
        u_gum = np.column_stack([out["u_north_arcsec"], out["u_east_arcsec"]]) / Z95
        rng = np.random.default_rng(seed)
        sigma = model.state["reading_sigma"]
        draws = []
        for p in rng.multivariate_normal(model.values(PARAMS), model.cov_of(PARAMS), size=4000):
            x = {c: meas[c] + rng.normal(0.0, sigma, 8) for c in mt.READING_COLUMNS}
            d1, d2 = mt.half_differences(x)
            draws.append(np.column_stack(mt.compensation(p, meas["azimuth_deg"], d1, d2, 180.0)))
        u_mc = np.std(np.array(draws), axis=0, ddof=1)
        assert np.all(np.abs(u_gum / u_mc - 1) < 0.1), (u_gum, u_mc)


def test_compensation_uncertainty_covers_the_error_of_repeated_calibrations():
    """End to end: new readings corrected with models from repeated calibrations scatter about the
    true axis tilt as the GUM uncertainty says (the reference's own noise is not part of a corrected
    value)."""
    data = load_scenario("seed004").model_dump()
    sc = parse_scenario(data)
    meas_data = {
        **data,
        "grid": {**data["grid"], "cycles": [{"north_arcsec": 20.0, "east_arcsec": -15.0}]},
    }
    meas_sc = parse_scenario(meas_data)
    errs, us = [], []
    for k in range(150):
        model = REVERSAL.fit(run_scenario(sc, seed=k).columns, FitOptions())
        meas = run_scenario(meas_sc, seed=90_000 + k)
        out = REVERSAL.correct(without_dof(model), meas.columns)
        errs.append(np.column_stack([out["north_arcsec"] - 20.0, out["east_arcsec"] + 15.0]))
        us.append(np.column_stack([out["u_north_arcsec"], out["u_east_arcsec"]]) / Z95)
    ratio = np.std(np.array(errs), axis=0) / np.mean(np.array(us), axis=0)
    assert np.all((ratio > 0.75) & (ratio < 1.25)), ratio
