"""Scenario files: presets, validation messages, and the JSON Schema in docs/."""

import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from service.errors import InputError
from service.physics.effects import EFFECTS_BY_KIND
from service.scenarios import json_schema, load_scenario, parse_scenario, preset_names, run_scenario

ROOT = Path(__file__).resolve().parents[1]
PRESETS = ["seed000", "seed002-b55", "seed002-b75", "seed002-sim", "seed003", "seed004"]


def test_every_preset_the_issue_names_is_shipped():
    assert set(PRESETS) <= set(preset_names())


def test_schema_in_docs_is_current():
    on_disk = json.loads((ROOT / "docs" / "scenario.schema.json").read_text())
    assert on_disk == json_schema(), (
        "regenerate: python -m service.scenarios schema > docs/scenario.schema.json"
    )


@pytest.mark.parametrize("name", PRESETS)
def test_presets_validate_against_the_published_schema(name):
    data = json.loads((ROOT / "service" / "scenarios" / "presets" / f"{name}.json").read_text())
    jsonschema.validate(data, json_schema())


def test_schema_states_every_effect_range():
    schema = json.dumps(json_schema())
    for kind, table in EFFECTS_BY_KIND.items():
        for eff in table.values():
            assert f"{kind.title()}_{eff.name}" in schema


def _stage(**over):
    d = {"kind": "stage", "grid": {"x_deg": [0, 3], "y_deg": [0, 3]}}
    d.update(over)
    return d


@pytest.mark.parametrize(
    "data,field,words",
    [
        (_stage(effects={"gremlins": {}}), "effects.gremlins", "unknown effect"),
        (
            _stage(effects={"backlash": {"x_deg": 5}}),
            "effects.backlash.x_deg",
            "less than or equal to 0.5",
        ),
        (_stage(effects={"backlash": {"z_deg": 0.1}}), "effects.backlash.z_deg", "unknown field"),
        ({"kind": "stage"}, "grid", "missing"),
        (_stage(grid={"x_deg": [0, 20], "y_deg": [0]}), "grid.x_deg", "beyond the stage travel"),
        (
            _stage(grid={"x_deg": {"start": 0, "stop": 3}, "y_deg": [0]}),
            "grid.x_deg",
            "exactly one of step or count",
        ),
        (_stage(seed=-1), "seed", "greater than or equal to 0"),
        ({"kind": "rotation", "grid": {"theta_deg": [0]}}, "bench", "missing"),
        ({"kind": "warp"}, "kind", "not one of"),
        (
            _stage(effects={"noise": {"ref_sigma_deg": "lots"}}),
            "effects.noise.ref_sigma_deg",
            "valid number",
        ),
        # JSON types are kept: a quoted number or a true is not an integer, "no" is not a boolean
        (_stage(seed="5"), "seed", "valid integer"),
        (_stage(seed=True), "seed", "valid integer"),
        (
            _stage(grid={"x_deg": [0], "y_deg": [0], "repeats": "2"}),
            "grid.repeats",
            "valid integer",
        ),
        (
            _stage(effects={"noise": {"ref_sigma_deg": "0.001"}}),
            "effects.noise.ref_sigma_deg",
            "valid number",
        ),
    ],
)
def test_bad_scenarios_get_one_line_naming_the_field(data, field, words):
    with pytest.raises(InputError) as exc:
        parse_scenario(data, source="s.json")
    msg = str(exc.value)
    assert "\n" not in msg
    assert f"field {field}:" in msg and words in msg


def test_an_integer_is_a_valid_number_of_degrees():
    sc = parse_scenario(
        _stage(effects={"backlash": {"x_deg": 0}}, grid={"x_deg": [-3, 0, 3], "y_deg": [0]})
    )
    assert sc.grid.x_deg == [-3.0, 0.0, 3.0]


def test_same_seed_same_data_other_seed_other_noise():
    sc = load_scenario("seed000")
    a, b, c = run_scenario(sc), run_scenario(sc), run_scenario(sc, seed=1)
    assert np.array_equal(a.columns["ref_x_deg"], b.columns["ref_x_deg"])
    assert not np.array_equal(a.columns["ref_x_deg"], c.columns["ref_x_deg"])
    assert np.array_equal(a.columns["stage_x_deg"], c.columns["stage_x_deg"])


def test_seed000_preset_has_papers_grid_and_uncorrected_errors_of_a_few_tenths():
    r = run_scenario(load_scenario("seed000"))
    c = r.columns
    # the commands are recorded as executed: the 3-deg grid in whole pulses of the bench
    grid_x, _ = r.bench.quantise(np.arange(-12, 13, 3.0), 0.0)
    assert len(c["point"]) == 81 and set(np.unique(c["stage_x_deg"])) == set(grid_x)
    assert r.bench.pulse_mismatch(c["stage_x_deg"], c["stage_y_deg"]) is None
    err_x = np.max(np.abs(c["stage_x_deg"] - c["meas_x_deg"]))
    err_y = np.max(np.abs(c["stage_y_deg"] - c["meas_y_deg"]))
    assert 0.2 < err_x < 0.9 and 0.1 < err_y < 0.5  # seed 000 §4.4: 0.559 and 0.216 deg


def test_serpentine_order_alternates_the_approach_of_the_upper_stage():
    r = run_scenario(load_scenario("seed000"))
    d = r.columns["dir_x"].reshape(9, 9)
    assert np.all(d[0, 1:] == 1) and np.all(d[1, 1:] == -1)


def test_physics_doc_lists_the_registry_as_it_is():
    from service.physics.effects import markdown_tables

    assert markdown_tables() in (ROOT / "docs" / "physics.md").read_text()


def _stage_variant(**grid):
    data = load_scenario("seed000").model_dump(mode="json", exclude_defaults=True)
    data["grid"].update(grid)
    return parse_scenario(data)


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_one_positioning_draw_per_move_shared_by_both_sensors_and_by_the_readings_at_a_stand(seed):
    """Each row is a move (its own draw of the stage's positioning error); with readings_per_stand
    the rows read at one stand share the draw. Both sensors see the same table, so their
    within-stand scatter is their reading noise alone, and the true tilt is constant at a stand."""
    sc = _stage_variant(
        readings_per_stand=4,
        x_deg={"start": -12, "stop": 12, "step": 2},
        y_deg={"start": -12, "stop": 12, "step": 2},
    )
    run = run_scenario(sc, seed=seed)
    c, t = run.columns, run.truth
    per = 4
    n = c["point"].size
    assert n == 13 * 13 * per
    stand = np.arange(n) // per
    # one stand: one grid point
    assert np.all(c["point"].reshape(-1, per) == c["point"][::per, None])
    for k in ("tilt_x_deg", "tilt_y_deg", "actual_x_deg", "actual_y_deg"):
        # the table stands still while it is read
        assert np.ptp(t[k].reshape(-1, per), axis=1).max() == 0.0
    assert np.all(np.diff(c["t_s"]) > 0)
    fx = run.effects
    sig_ref, sig_meas = fx.get("noise", "ref_sigma_deg"), fx.get("noise", "meas_sigma_deg")
    for a in ("x", "y"):
        # the reference reads the table plus its own noise: its within-stand sd is that noise, not
        # more
        dr = (c[f"ref_{a}_deg"] - t[f"tilt_{a}_deg"]).reshape(-1, per)
        s_ref = np.sqrt(
            np.sum((dr - dr.mean(axis=1, keepdims=True)) ** 2) / (dr.size - dr.shape[0])
        )
        assert 0.9 * sig_ref < s_ref < 1.1 * sig_ref  # 507 dof: sd of s/σ is 3 %
        # the difference of the two sensors at a stand: their two noises combined, no stage term
        d = (c[f"meas_{a}_deg"] - c[f"ref_{a}_deg"]).reshape(-1, per)
        s_d = np.sqrt(np.sum((d - d.mean(axis=1, keepdims=True)) ** 2) / (d.size - d.shape[0]))
        assert 0.9 < s_d / np.hypot(sig_ref, sig_meas) < 1.1
    # between moves the table does move: the positioning error (stage_sigma_deg) is drawn once per
    # stand
    sigma_stage = fx.get("noise", "stage_sigma_deg")
    noiseless = run_scenario(sc, seed=seed, noiseless=True).truth
    dev = (t["actual_x_deg"] - noiseless["actual_x_deg"])[::per]
    assert 0.85 < np.std(dev) / sigma_stage < 1.15
    assert stand.size == n


def test_one_reading_per_stand_keeps_the_rows_as_they_were():
    """readings_per_stand = 1 (the default) is a row per move, the same draws as before it
    existed."""
    a = run_scenario(load_scenario("seed000"), seed=4).columns
    b = run_scenario(_stage_variant(readings_per_stand=1), seed=4).columns
    assert all(np.array_equal(a[k], b[k]) for k in a)
