"""Data that cannot support a candidate skip it with a reason; data too thin for a baseline are
refused."""

import numpy as np
import pytest

from benchmarks.hidden_effects import bench_with_hidden
from service.discrepancy.stage import stage_report
from service.errors import InputError


@pytest.fixture(scope="module")
def bench():
    return bench_with_hidden(0, {})


def _cols(hb, drop=(), **replace):
    cols = {k: np.asarray(v, dtype=float) for k, v in hb.columns.items() if k not in drop}
    cols.update(replace)
    return cols


def skipped(rep):
    return {s["effect"]: s["reason"] for s in rep["skipped"]}


def test_no_temperature_column(bench):
    rep, _, _ = stage_report(_cols(bench, drop=("temp_c",)), noise_sigma=bench.sigma_deg)
    assert "no temp_c column" in skipped(rep)["temperature_drift"]


def test_constant_temperature(bench):
    rep, _, _ = stage_report(_cols(bench, temp_c=np.full(81, 21.0)), noise_sigma=bench.sigma_deg)
    assert "temperature constant" in skipped(rep)["temperature_drift"]


def test_single_approach_direction(bench):
    ones = np.ones(81)
    rep, _, _ = stage_report(_cols(bench, dir_x=ones, dir_y=ones), noise_sigma=bench.sigma_deg)
    assert "single approach direction" in skipped(rep)["backlash"]


def test_no_direction_columns(bench):
    rep, _, _ = stage_report(_cols(bench, drop=("dir_x", "dir_y")), noise_sigma=bench.sigma_deg)
    assert "no dir_x/dir_y columns" in skipped(rep)["backlash"]


def test_no_time_column(bench):
    rep, _, _ = stage_report(_cols(bench, drop=("t_s",)), noise_sigma=bench.sigma_deg)
    assert "no t_s column" in skipped(rep)["time_drift"]


def test_only_separable_parameters_are_fitted(bench):
    # serpentine: the y stage always moves the same way, so only the x backlash can be seen
    rep, _, _ = stage_report(_cols(bench), noise_sigma=bench.sigma_deg)
    assert any(n.startswith("backlash: parameter y_deg left out") for n in rep["notes"])


def test_grid_on_whole_worm_turns_cannot_show_periodic_error():
    # 1.125 deg steps are whole turns of the upper worm and 1.6 deg steps two turns of the lower
    # one: every point samples the same worm phase
    x = np.arange(-4, 5) * 1.125
    y = np.arange(-4, 5) * 1.6
    X, Y = (a.ravel() for a in np.meshgrid(x, y))
    cols = {
        "stage_x_deg": X,
        "stage_y_deg": Y,
        "ref_x_deg": np.degrees(np.arcsin(np.sin(np.radians(X)) * np.cos(np.radians(Y)))) + 0.01,
        "ref_y_deg": Y - 0.02,
    }
    rng = np.random.default_rng(0)
    cols["ref_x_deg"] = cols["ref_x_deg"] + rng.normal(0, 0.002, X.size)
    cols["ref_y_deg"] = cols["ref_y_deg"] + rng.normal(0, 0.002, X.size)
    rep, _, _ = stage_report(cols, noise_sigma=0.002)
    assert "periodic_error" in skipped(rep)
    assert "not separable" in skipped(rep)["periodic_error"]
    assert rep["named_effects"] == ["offaxis_coupling"]


def test_too_few_points_skip_candidates_with_the_count(bench):
    # seven points spread over the grid: room for the coupling only
    keep = [0, 13, 26, 40, 53, 66, 80]
    cols = {k: v[keep] for k, v in _cols(bench).items()}
    rep, _, _ = stage_report(cols, noise_sigma=bench.sigma_deg)
    reasons = skipped(rep)
    assert rep["named_effects"] == ["offaxis_coupling"]
    assert all("too few points" in r for r in reasons.values()) and len(reasons) == 5, reasons


def test_fewer_points_than_a_baseline_needs_is_an_input_error(bench):
    cols = {k: v[:5] for k, v in _cols(bench).items()}
    with pytest.raises(InputError, match="at least 6 points"):
        stage_report(cols, noise_sigma=bench.sigma_deg)


def test_noise_from_repeated_points_is_preferred():
    from service.scenarios import parse_scenario, run_scenario

    hb = bench_with_hidden(2, {})
    # a second pass over the same points, later in time
    sc = dict(hb.scenario)
    sc["grid"] = dict(sc["grid"], repeats=2)
    run = run_scenario(parse_scenario(sc), seed=2)
    rep, _, _ = stage_report(run.columns, noise_sigma=None)
    assert rep["noise_source"] == "repeated points"
    assert rep["noise_dof"] >= 5
    assert 0.5 * hb.sigma_deg < rep["noise_level"][0] < 2.0 * hb.sigma_deg


def test_without_repeats_or_specification_the_noise_is_the_final_residual(bench):
    rep, _, _ = stage_report(_cols(bench), noise_sigma=None)
    assert rep["noise_source"] == "final residual"
    assert rep["steps"][0]["evidence"]["test"] == "F"


@pytest.mark.parametrize("baseline", ["linear", "kinematic"])
def test_a_candidate_the_design_hides_is_said_with_what_would_show_it(bench, baseline):
    """On one serpentine pass time runs with the rows: a drift is mostly the bench's geometry, and
    the report says how much of it the test can see and which design would separate it; in random
    order it is not flagged."""
    rep, _, _ = stage_report(_cols(bench), noise_sigma=bench.sigma_deg, baseline=baseline)
    frac = rep["separability"]["time_drift"]["ref_x_deg_per_h"]
    assert 0.02 < frac < 0.25
    (note,) = [n for n in rep["notes"] if n.startswith("time_drift: parameter ref_x_deg_per_h")]
    assert f"{100 * frac:.1f} % visible" in note and "random order" in note
    assert f"about {1 / frac:.0f} times larger" in note

    shuffled = bench_with_hidden(0, {}, design="random")
    rep, _, _ = stage_report(_cols(shuffled), noise_sigma=shuffled.sigma_deg, baseline=baseline)
    assert rep["separability"]["time_drift"]["ref_x_deg_per_h"] > 0.25
    assert not any(n.startswith("time_drift") for n in rep["notes"])
