"""Stage methods: exact round trips on benches each can represent, recovery, robustness,
MODEL.json."""

import json

import numpy as np
import pytest

from service.calibration.model import CalibrationModel
from service.calibration.registry import FitOptions, get_method, methods_for
from service.errors import DegenerateDataError, InputError
from service.physics.effects import EffectSet
from service.physics.stage import StageBench, StageGeometry, simulate_stage
from service.scenarios import load_scenario

STAGE_METHODS = ("homography", "coupling", "axis-transform", "kinematic")
PRESET_EFFECTS = {
    k: v
    for k, v in load_scenario("seed000").model_dump()["effects"].items()
    if v is not None and k != "noise"
}


def _grid(step=3.0, lim=12.0):
    g = np.arange(-lim, lim + 1e-9, step)
    x, y = np.meshgrid(g, g)
    return x.ravel(), y.ravel()


def _dataset(bench, fx, step=3.0, lim=12.0):
    """Noise-free bench data; commands already whole pulses, so the simulator's rounding is a
    no-op."""
    cx, cy = bench.quantise(*_grid(step, lim))
    sim = simulate_stage(bench, fx, cx, cy, np.ones_like(cx), np.ones_like(cy))
    cols = {
        "stage_x_deg": cx,
        "stage_y_deg": cy,
        "dir_x": np.ones_like(cx),
        "dir_y": np.ones_like(cy),
    }
    cols.update({k: sim[k] for k in ("ref_x_deg", "ref_y_deg", "meas_x_deg", "meas_y_deg")})
    return cols, sim


def _true_tilt(bench, fx, cmd_x, cmd_y):
    """Table tilt for unrounded commands, from the simulator's geometry; stage scale applied by
    hand."""
    geo = StageGeometry.from_effects(bench, fx)
    ax = np.asarray(cmd_x) * (1 + fx.get("stage_scale", "x"))
    ay = np.asarray(cmd_y) * (1 + fx.get("stage_scale", "y"))
    r = geo.readings_deg(np.radians(ax), np.radians(ay))
    return r["tilt_x"], r["tilt_y"]


REPRESENTABLE = {
    # H1 on the cross + eq. (10) is exact for a bench whose only errors leave the stage-to-reference
    # map projective once decoupled; H2 is exact for an affine measurement sensor.
    "homography": {
        "zero_offset": {"meas_x_deg": 0.03, "meas_y_deg": -0.02},
        "scale_factor": {"meas_x": 0.004, "meas_y": -0.003},
    },
    # the bare stacked geometry, nothing else
    "coupling": {},
    # no coupling (idealised bench), sensing axes turned in the table plane only
    "axis-transform": {
        "offaxis_coupling": {"enabled": False},
        "sensor_yaw": {"ref_deg": 0.4, "meas_deg": -0.6},
        "non_orthogonality": {"meas_deg": 0.3},
    },
    # the full seed 000 bench, every effect of the preset except its noise
    "kinematic": PRESET_EFFECTS,
}


@pytest.mark.parametrize("method", STAGE_METHODS)
def test_level_and_correct_round_trip_on_a_bench_the_method_represents(method):
    bench = StageBench()
    fx = EffectSet.from_mapping("stage", REPRESENTABLE[method])
    cols, _ = _dataset(bench, fx)
    m = get_method("stage", method)
    model = m.fit(cols, FitOptions())
    tx, ty = _grid(2.5, 10.0)
    tx, ty = tx + 0.37, ty - 0.21  # not the calibration points
    cmd = m.level(model, {"target_x_deg": tx, "target_y_deg": ty})
    X, Y = _true_tilt(bench, fx, cmd["stage_x_deg"], cmd["stage_y_deg"])
    assert np.max(np.abs(X - tx)) < 2e-8 and np.max(np.abs(Y - ty)) < 2e-8
    # correct: readings at those commands back to the true tilt
    sim = simulate_stage(bench, fx, *bench.quantise(cmd["stage_x_deg"], cmd["stage_y_deg"]))
    out = m.correct(model, {"meas_x_deg": sim["meas_x_deg"], "meas_y_deg": sim["meas_y_deg"]})
    assert np.max(np.abs(out["tilt_x_deg"] - sim["tilt_x_deg"])) < 2e-8
    assert np.max(np.abs(out["tilt_y_deg"] - sim["tilt_y_deg"])) < 2e-8


def test_stage_methods_are_registered():
    assert set(STAGE_METHODS) <= set(methods_for("stage"))


def test_kinematic_recovers_the_identifiable_parameters():
    """Noise-free seed 000 bench: the fit lands on the gauge-reduced truth.

    Held by the gauge: lower yaw (0.2) goes into perpendicularity (0.3 - 0.2) and ref yaw (0.3 -
    0.2); the reference seat (0.03, -0.02) goes into the top (0.05 + 0.03, 0.04 - 0.02). The
    measurement sensor is described relative to the reference: yaw -0.45 - 0.3, seat (0.06 - 0.03,
    -0.05 + 0.02). Tolerances are the second-order terms of composing small rotations (a few 1e-4
    deg).
    """
    bench = StageBench()
    fx = EffectSet.from_mapping("stage", PRESET_EFFECTS)
    cols, _ = _dataset(bench, fx)
    model = get_method("stage", "kinematic").fit(cols, FitOptions())
    v = {k: p.value for k, p in model.parameters.items()}
    assert abs(v["stage_scale.x"] - 0.003) < 1e-7 and abs(v["stage_scale.y"] + 0.002) < 1e-7
    assert abs(v["axis_misalignment.perpendicularity_deg"] - 0.1) < 2e-4
    assert abs(v["sensor_yaw.ref_deg"] - 0.1) < 2e-4
    assert (
        abs(v["mounting_tilt.desk_x_deg"] - 0.12) < 1e-3
        and abs(v["mounting_tilt.desk_y_deg"] + 0.08) < 1e-3
    )
    assert (
        abs(v["mounting_tilt.top_x_deg"] - 0.08) < 1e-3
        and abs(v["mounting_tilt.top_y_deg"] - 0.02) < 1e-3
    )
    assert abs(v["backlash.x_deg"]) < 1e-6
    assert (
        abs(v["sensor_yaw.meas_deg"] + 0.75) < 2e-4
        and abs(v["non_orthogonality.meas_deg"] - 0.25) < 2e-4
    )
    assert (
        abs(v["zero_offset.meas_x_deg"] - 0.02) < 1e-3
        and abs(v["zero_offset.meas_y_deg"] + 0.015) < 1e-3
    )
    assert (
        abs(v["mounting_tilt.meas_x_deg"] - 0.03) < 1e-3
        and abs(v["mounting_tilt.meas_y_deg"] + 0.03) < 1e-3
    )
    assert abs(v["scale_factor.meas_x"]) < 1e-6 and abs(v["scale_factor.meas_y"]) < 1e-6
    held = {k for k, p in model.parameters.items() if p.fixed}
    assert held == {
        "axis_misalignment.lower_yaw_deg",
        "axis_misalignment.lower_pitch_deg",
        "axis_misalignment.upper_pitch_deg",
        "mounting_tilt.ref_x_deg",
        "mounting_tilt.ref_y_deg",
        # every point approached from below: backlash = desk tilt
        "backlash.x_deg",
        "backlash.y_deg",
    }
    for k in held:
        assert "held at 0" in model.parameters[k].note and any(k in n for n in model.notes)
    assert model.covariance is not None and len(model.covariance_names) == model.covariance.shape[0]


def test_kinematic_held_parameters_lose_nothing_on_a_bench_that_has_them():
    """Lower/upper pitch and lower yaw are gauge: a bench with them is reproduced exactly without
    them."""
    eff = dict(PRESET_EFFECTS)
    eff["axis_misalignment"] = {
        "lower_yaw_deg": 0.5,
        "lower_pitch_deg": 0.3,
        "perpendicularity_deg": -0.2,
        "upper_pitch_deg": -0.4,
    }
    bench = StageBench()
    fx = EffectSet.from_mapping("stage", eff)
    cols, _ = _dataset(bench, fx)
    m = get_method("stage", "kinematic")
    model = m.fit(cols, FitOptions())
    assert model.residuals["columns"]["ref_x_deg"]["rms"] < 1e-9
    tx, ty = _grid(4.0, 12.0)
    cmd = m.level(model, {"target_x_deg": tx, "target_y_deg": ty})
    X, Y = _true_tilt(bench, fx, cmd["stage_x_deg"], cmd["stage_y_deg"])
    assert np.max(np.abs(X - tx)) < 2e-8 and np.max(np.abs(Y - ty)) < 2e-8


@pytest.mark.parametrize("flip", ["x", "y"])
def test_upside_down_measurement_sensor(flip):
    bench = StageBench(meas_flip=flip)
    fx = EffectSet.from_mapping("stage", PRESET_EFFECTS)
    cols, _ = _dataset(bench, fx)
    sim = simulate_stage(bench, fx, *bench.quantise(*_grid(2.5, 10.0)))
    for method in ("kinematic", "homography", "axis-transform", "coupling"):
        m = get_method("stage", method)
        model = m.fit(cols, FitOptions())
        out = m.correct(model, {"meas_x_deg": sim["meas_x_deg"], "meas_y_deg": sim["meas_y_deg"]})
        err = np.hypot(out["tilt_x_deg"] - sim["tilt_x_deg"], out["tilt_y_deg"] - sim["tilt_y_deg"])
        bound = {"kinematic": 1e-8, "homography": 0.01, "axis-transform": 0.1, "coupling": 0.5}[
            method
        ]
        # mirrored: an unflipped model would be off by twice the angle
        assert err.max() < bound, method
        if method != "homography":  # H2 simply carries the sign
            assert any("upside down" in n for n in model.notes)
    # stated by the lab: accepted when it agrees with the data, refused when it does not
    km = get_method("stage", "kinematic")
    km.fit(cols, FitOptions(extra={"meas_flip": flip}))
    with pytest.raises(DegenerateDataError, match="contradicts"):
        km.fit(cols, FitOptions(extra={"meas_flip": "none"}))


VARIANTS = [(m, {}) for m in STAGE_METHODS] + [
    ("homography", {"points": "all"}),
    ("homography", {"offaxis": "paper"}),
]


@pytest.mark.parametrize(
    "method,extra", VARIANTS, ids=[f"{m}-{'-'.join(e.values()) or 'default'}" for m, e in VARIANTS]
)
def test_model_json_round_trip_gives_identical_predictions(method, extra):
    from service.scenarios import run_scenario

    cols = run_scenario(load_scenario("seed000"), seed=5).columns
    m = get_method("stage", method)
    model = m.fit(cols, FitOptions(extra=extra))
    back = CalibrationModel.from_json_dict(
        json.loads(json.dumps(model.to_json_dict(), allow_nan=False))
    )
    meas = {"meas_x_deg": cols["meas_x_deg"], "meas_y_deg": cols["meas_y_deg"]}
    a, b = m.correct(model, meas), m.correct(back, meas)
    # the tilt, its expanded uncertainties and their coverage factors (95 %: Student's t, at least
    # the normal 1.96)
    assert (
        set(a)
        == set(b)
        == {"tilt_x_deg", "tilt_y_deg", "u_tilt_x_deg", "u_tilt_y_deg", "k_tilt_x", "k_tilt_y"}
    )
    if {"meas_uncorrected_bias_deg", "meas_misfit_p95_deg", "meas_misfit_score_p95"} & set(
        model.state
    ):
        # a bias the model keeps (U the folded normal's 95 % point, k = U / √(b² + u²)), or the
        # error it leaves bounded by its size over the points (k = that bound / their RMS): k ≥ 1
        assert np.all(a["k_tilt_x"] >= 1.0) and np.all(a["k_tilt_y"] >= 1.0)
    else:
        assert np.all(a["k_tilt_x"] >= 1.959) and np.all(a["k_tilt_y"] >= 1.959)
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    t = {"target_x_deg": np.array([0.0, 11.0, -7.5]), "target_y_deg": np.array([0.0, -11.0, 9.0])}
    la, lb = m.level(model, t), m.level(back, t)
    for k in la:
        assert np.array_equal(la[k], lb[k]), k


def test_homography_uses_the_cross_and_says_so():
    from service.scenarios import run_scenario

    cols = run_scenario(load_scenario("seed000"), seed=3).columns
    m = get_method("stage", "homography")
    model = m.fit(cols, FitOptions())
    assert model.fit["n_points_h1"] == 17 and any("the cross" in n for n in model.notes)
    assert any("exact inverse" in n for n in model.notes) and any(
        "0.0062" in n for n in model.notes
    )
    off_cross = (cols["stage_x_deg"] != 0) & (cols["stage_y_deg"] != 0)
    no_cross = {k: v[off_cross] for k, v in cols.items()}
    model2 = m.fit(no_cross, FitOptions())
    assert model2.fit["n_points_h1"] == 64 and any("lack the cross" in n for n in model2.notes)


def test_robust_loss_resists_outliers():
    from service.scenarios import run_scenario

    cols = {
        k: np.array(v, dtype=float)
        for k, v in run_scenario(load_scenario("seed000"), seed=8).columns.items()
    }
    m = get_method("stage", "kinematic")
    clean = m.fit(cols, FitOptions())
    bad = {k: v.copy() for k, v in cols.items()}
    bad["ref_x_deg"][[10, 40, 70]] += 0.3  # three bumped reference readings
    bad["meas_y_deg"][[5, 50]] -= 0.2  # and two measurement readings
    t = {"target_x_deg": np.array([-12.0, 0.0, 12.0]), "target_y_deg": np.array([12.0, 0.0, -12.0])}
    ref_level = m.level(clean, t)["stage_x_deg"]
    ref_tilt = m.correct(clean, cols)["tilt_y_deg"]
    dev = {}
    for loss in ("linear", "soft_l1", "huber", "cauchy"):
        model = m.fit(bad, FitOptions(loss=loss))
        dev[loss] = (
            np.max(np.abs(m.level(model, t)["stage_x_deg"] - ref_level)),
            np.max(np.abs(m.correct(model, cols)["tilt_y_deg"] - ref_tilt)),
        )
    for loss in ("soft_l1", "huber", "cauchy"):
        assert dev[loss][0] < dev["linear"][0] / 3 and dev[loss][1] < dev["linear"][1] / 3, (
            loss,
            dev,
        )
    with pytest.raises(InputError, match="loss"):
        m.fit(cols, FitOptions(loss="tukey"))


def test_degenerate_inputs_are_refused_with_what_is_missing():
    from service.scenarios import run_scenario

    cols = run_scenario(load_scenario("seed000"), seed=1).columns
    on_x_line = {k: v[cols["stage_y_deg"] == 0] for k, v in cols.items()}
    for method in STAGE_METHODS:
        with pytest.raises(DegenerateDataError) as exc:
            get_method("stage", method).fit(on_x_line, FitOptions())
        assert (
            "line" in str(exc.value)
            or "stage_y_deg" in str(exc.value)
            or "lower stage" in str(exc.value)
        )
    few = {k: v[:4] for k, v in cols.items()}
    with pytest.raises(DegenerateDataError):
        get_method("stage", "kinematic").fit(few, FitOptions())
    with pytest.raises(DegenerateDataError, match="did not converge"):
        get_method("stage", "kinematic").fit(cols, FitOptions(extra={"max_nfev": 1}))
    km = get_method("stage", "kinematic")
    with pytest.raises(InputError, match="travel"):
        km.level(
            km.fit(cols, FitOptions()),
            {"target_x_deg": np.array([0.0, 14.9]), "target_y_deg": np.array([0.0, 14.0])},
        )
    no_meas = {k: v for k, v in cols.items() if not k.startswith("meas_")}
    for method in STAGE_METHODS:
        m = get_method("stage", method)
        model = m.fit(no_meas, FitOptions())
        m.level(model, {"target_x_deg": np.array([1.0]), "target_y_deg": np.array([2.0])})
        with pytest.raises(InputError, match="without meas_x_deg"):
            m.correct(model, {"meas_x_deg": np.array([1.0]), "meas_y_deg": np.array([2.0])})


def test_homography_on_four_points_has_no_covariance_rather_than_a_zero_one():
    """Four points solve H2 exactly: no residual is left to estimate the noise, so no u_tilt is
    claimed."""
    sx, sy = np.array([-3.0, 3.0, -3.0, 3.0]), np.array([-3.0, -3.0, 3.0, 3.0])
    cols = {
        "stage_x_deg": sx,
        "stage_y_deg": sy,
        "ref_x_deg": sx + 0.01 * sy,
        "ref_y_deg": sy,
        "meas_x_deg": sx + 0.003 * sy + 0.1,
        "meas_y_deg": sy - 0.002 * sx,
    }
    m = get_method("stage", "homography")
    model = m.fit(cols, FitOptions(extra={"points": "all"}))
    assert (
        model.covariance is None
        and model.fit["h2"]["dof"] == 0
        and model.fit["h2"]["sigma_deg"] is None
    )
    out = m.correct(model, {"meas_x_deg": np.array([1.0]), "meas_y_deg": np.array([2.0])})
    assert set(out) == {"tilt_x_deg", "tilt_y_deg"}
    back = CalibrationModel.from_json_dict(json.loads(json.dumps(model.to_json_dict())))
    assert set(
        m.correct(back, {"meas_x_deg": np.array([1.0]), "meas_y_deg": np.array([2.0])})
    ) == set(out)


@pytest.mark.parametrize("method", STAGE_METHODS)
def test_every_stage_method_refuses_targets_the_bench_cannot_reach(method):
    from service.scenarios import run_scenario

    cols = run_scenario(load_scenario("seed000"), seed=2).columns
    m = get_method("stage", method)
    model = m.fit(cols, FitOptions())
    out = m.level(
        model, {"target_x_deg": np.array([-12.0, 12.0]), "target_y_deg": np.array([12.0, -12.0])}
    )
    assert np.all(np.abs(out["stage_x_deg"]) <= 15.0) and np.all(np.abs(out["stage_y_deg"]) <= 15.0)
    for tx, ty in ((20.0, 0.0), (0.0, -16.0), (89.0, 89.0)):
        with pytest.raises(InputError, match="row"):
            m.level(
                model, {"target_x_deg": np.array([0.0, tx]), "target_y_deg": np.array([0.0, ty])}
            )
