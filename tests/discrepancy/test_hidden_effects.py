"""The workflow names what the simulator hid, and nothing else (a few seeds of every case).

The many-seed figures are benchmarks/sweep_discrepancy.py's; these seeds only guard the
behaviour. Sizes are multiples of the noise (benchmarks/hidden_effects.py).
"""

import pytest

from benchmarks.hidden_effects import VARIANTS, bench_with_hidden
from service.discrepancy.stage import stage_report

SEEDS = (0, 1)


def run(hidden, seed, baseline="linear", design="serpentine"):
    hb = bench_with_hidden(seed, hidden, design)
    rep, _, _ = stage_report(hb.columns, "ref", baseline, hb.sigma_deg)
    return rep, hb


def others(rep, hidden):
    want = {VARIANTS[v][0] for v in hidden}
    return set(rep["named_effects"]) - want - {"offaxis_coupling"}


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("baseline", ["linear", "kinematic"])
def test_no_hidden_effect_names_nothing_but_the_geometry(baseline, seed):
    rep, _ = run({}, seed, baseline)
    expected = ["offaxis_coupling"] if baseline == "linear" else []
    assert rep["named_effects"] == expected
    assert rep["stop"]["reason"].startswith("no further effect")
    assert rep["noise_source"] == "instrument specification"
    assert rep["final_vs_noise"]["p_value"] > 0.01  # the gap is closed to the noise level
    if baseline == "linear":  # coupling is always there on a stacked bench and is found first
        step = rep["steps"][0]
        assert step["magnitude"]["kappa"]["value"] == pytest.approx(1.0, abs=0.05)
        assert step["rms_after"][0] < step["rms_before"][0] / 10


# a y-axis quadratic is the linear baseline's blind spot (perspective term + level tilt): checked
# separately
LINEAR_VISIBLE = [v for v in VARIANTS if v not in ("sensor_nonlinearity_y", "time_drift")]


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("variant", LINEAR_VISIBLE)
def test_linear_baseline_names_each_hidden_effect_at_5_noise(variant, seed):
    rep, hb = run({variant: 5.0}, seed)
    effect = VARIANTS[variant][0]
    assert rep["named_effects"][0] == "offaxis_coupling"
    assert effect in rep["named_effects"]
    assert not others(rep, {variant: 5})
    assert rep["final_vs_noise"]["p_value"] > 0.01


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_kinematic_baseline_names_each_hidden_effect(variant, seed):
    # time drift on one serpentine pass is mostly a change of the bench's own parameters: random
    # order shows it
    design = "random" if variant == "time_drift" else "serpentine"
    rep, _ = run({variant: 5.0}, seed, "kinematic", design)
    assert VARIANTS[variant][0] in rep["named_effects"]
    assert not others(rep, {variant: 5})


@pytest.mark.parametrize("seed", SEEDS)
def test_time_drift_on_a_serpentine_pass_is_named_when_large_enough(seed):
    rep, _ = run({"time_drift": 15.0}, seed)
    assert "time_drift" in rep["named_effects"]
    rep, _ = run({"time_drift": 5.0}, seed, design="random")
    assert "time_drift" in rep["named_effects"]


def test_linear_baseline_flags_the_y_quadratic_as_poorly_separable_instead_of_guessing():
    rep, _ = run({"sensor_nonlinearity_y": 5.0}, 0)
    assert not others(rep, {})  # names nothing wrong
    assert rep["separability"]["sensor_nonlinearity"]["ref_y_per_deg"] < 0.05
    assert any("ref_y_per_deg is poorly separable" in n for n in rep["notes"])


@pytest.mark.parametrize(
    "pair,baseline",
    [
        (("backlash", "periodic_error"), "linear"),
        (("sensor_nonlinearity", "temperature_drift"), "linear"),
        (("backlash", "temperature_drift"), "kinematic"),
        (("periodic_error", "sensor_nonlinearity"), "kinematic"),
    ],
)
def test_pairs_are_both_named(pair, baseline):
    for seed in SEEDS:
        hidden = {v: 5.0 for v in pair}
        rep, _ = run(hidden, seed, baseline)
        assert set(pair) <= set(rep["named_effects"]), rep["named_effects"]
        assert not others(rep, hidden)
        assert len(rep["steps"]) == len(pair) + (baseline == "linear")
        # each step shrinks the gap
        for st in rep["steps"]:
            assert sum(st["rms_after"]) < sum(st["rms_before"])


def test_fitted_magnitude_is_in_the_effects_own_units_with_an_honest_uncertainty():
    rep, hb = run({"backlash": 8.0}, 3)
    step = next(s for s in rep["steps"] if s["effect"] == "backlash")
    m = step["magnitude"]["x_deg"]
    assert m["unit"] == "deg"
    true_width = hb.params["backlash"]["x_deg"]
    assert abs(m["value"] - true_width) < 4 * m["uncertainty"]
    assert 0 < m["uncertainty"] < 0.2 * true_width
    assert step["summary"].startswith("backlash: x_deg = ")
    ev = step["evidence"]
    assert ev["p_value"] < ev["alpha"] and ev["delta_bic"] < 0 and ev["significant"]


def test_where_says_what_a_metrologist_would_write():
    rep, _ = run({"backlash": 5.0}, 0)
    # before anything is added the coupling dominates, at large |θx| growing with |θy|
    assert any("θx·θy²" in w for w in rep["where"])
    step = next(s for s in rep["steps"] if s["effect"] == "backlash")
    assert any("approach direction of the x stage" in w for w in step["evidence"]["where_before"])
    assert rep["where_final"][0].startswith("no structure left")


@pytest.mark.parametrize("seed", SEEDS)
def test_an_adaptive_record_still_shows_a_reference_quadratic_and_names_nothing_false(seed):
    """The adaptive job's 4 x 4 spread of 50-reading means (docs/discrepancy.md, "Records made
    adaptively"): the x quadratic it still sees, and nothing it does not hold."""
    rep, hb = run({"sensor_nonlinearity": 5.0}, seed, "kinematic", "adaptive")
    assert len(hb.columns["ref_x_deg"]) == 16
    assert "sensor_nonlinearity" in rep["named_effects"]
    assert not others(rep, {"sensor_nonlinearity": 5.0})


def test_a_size_the_bench_description_cannot_hold_is_said_not_run():
    """A time drift that would change a nine-point record by 5 x noise is faster than a bench
    allows: the sweep says so instead of failing or counting a miss as a run."""
    from benchmarks.sweep_discrepancy import one_run

    row = one_run(
        {"hidden": {"time_drift": 5.0}, "seed": 0, "design": "adaptive3", "baseline": "kinematic"}
    )
    assert "time_drift" in row["unrepresentable"] and row["hit"] is False
