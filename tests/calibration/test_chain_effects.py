"""Effects added to the kinematic chain: well posed from a start at zero, fitted as far as the
points determine them, and the reference's own errors taken out of its readings exactly."""

from __future__ import annotations

import numpy as np
import pytest

from service.calibration.methods.stage import reference
from service.calibration.methods.stage.kinematic import KINEMATIC
from service.calibration.registry import FitOptions
from service.calibration.stage_effect_fit import registry_effects
from service.discrepancy.adopt import NotAdoptable, adopted_model
from service.discrepancy.design import needs_of, plan_measurement
from service.discrepancy.stage_data import StageData
from service.physics.effects import EffectSet
from service.physics.inclinometer import apply_reading_errors
from service.physics.stage import StageBench, simulate_stage
from tests.helpers.benches import scenario

BENCH = StageBench(upper_gear_ratio=180, lower_gear_ratio=360)


def columns(
    effects: dict, xs: np.ndarray, ys: np.ndarray, seed: int = 3, n: int = 8, env_temp=None
) -> dict:
    """A job's columns on the 180:1 / 360:1 bench: means of n readings at each point, approached
    from below."""
    data = scenario("180-360", effects)
    fx = EffectSet.from_mapping("stage", data["effects"])
    X, Y = (a.ravel() for a in np.meshgrid(xs, ys))
    qx, qy = BENCH.quantise(X, Y)
    rng = np.random.default_rng(seed)
    temp = np.full(qx.size, 21.0) if env_temp is None else env_temp(np.arange(qx.size))
    out = {k: [] for k in ("ref_x_deg", "ref_y_deg", "meas_x_deg", "meas_y_deg")}
    for i in range(qx.size):
        sim = simulate_stage(
            BENCH,
            fx,
            np.full(n, qx[i]),
            np.full(n, qy[i]),
            1.0,
            1.0,
            np.full(n, temp[i]),
            np.full(n, 30.0 * i),
            rng=rng,
        )
        for k in out:
            out[k].append(float(np.mean(sim[k])))
    cols = {k: np.array(v) for k, v in out.items()}
    cols.update(
        stage_x_deg=qx,
        stage_y_deg=qy,
        dir_x=np.ones(qx.size),
        dir_y=np.ones(qx.size),
        point=np.arange(qx.size, dtype=float),
        t_s=1.8e9 + 30.0 * np.arange(qx.size),
        temp_c=temp,
    )
    return cols


def test_a_sine_cosine_pair_is_the_registry_s_amplitude_and_phase():
    pair = registry_effects({"periodic_error": {"x_sin_deg": 0.006, "x_cos_deg": -0.008}})
    assert pair["periodic_error"]["x_amp_deg"] == pytest.approx(0.010)
    fx_pair = EffectSet.from_mapping("stage", pair)
    fx_amp = EffectSet.from_mapping(
        "stage",
        {
            "periodic_error": {
                "x_amp_deg": 0.010,
                "x_phase_deg": float(np.degrees(np.arctan2(-0.008, 0.006))),
            }
        },
    )
    x = np.linspace(-3, 3, 61)
    a = simulate_stage(BENCH, fx_pair, x, 0 * x)["tilt_x_deg"]
    b = simulate_stage(BENCH, fx_amp, x, 0 * x)["tilt_x_deg"]
    np.testing.assert_allclose(a, b, atol=1e-12)


def test_worm_error_on_a_dense_x_scan_is_fitted_from_zero_and_the_unsampled_worm_is_held():
    # the grid: 31 x positions 0.6 deg apart, 4 y positions 4 whole periods of the lower
    # worm apart
    cols = columns(
        {"periodic_error": {"x_amp_deg": 0.010, "x_phase_deg": 40.0}},
        np.linspace(-9, 9, 31),
        np.linspace(-6, 6, 4),
    )
    model = KINEMATIC.fit(cols, FitOptions(extra={"bench": BENCH, "effects": ["periodic_error"]}))
    worm = model.fit["periodic_error"]["x"]
    assert abs(worm["amplitude_deg"] - 0.010) < 4 * worm["u_amplitude_deg"] + 2e-4, worm
    assert abs(worm["phase_deg"] - 40.0) < 4 * worm["u_phase_deg"] + 2.0, worm
    for lab in ("y_sin_deg", "y_cos_deg"):
        p = model.parameters[f"periodic_error.{lab}"]
        assert p.fixed and p.value == 0.0 and "1 phase" in p.note, p
    assert any("periodic_error.y_sin_deg" in n for n in model.notes)
    assert model.fit["undetermined_effects"] == {}


def test_a_worm_seen_at_two_phases_is_not_adopted():
    # x steps of 1 deg: half the 180:1 worm's 2-deg period
    cols = columns(
        {"periodic_error": {"x_amp_deg": 0.010, "x_phase_deg": 40.0}},
        np.linspace(-6, 6, 13),
        np.linspace(-6, 6, 5),
    )
    model = KINEMATIC.fit(
        cols, FitOptions(extra={"bench": BENCH, "effects": ["periodic_error"], "worm_axes": ["x"]})
    )
    assert "periodic_error" in model.fit["undetermined_effects"]
    assert "2 phases" in model.parameters["periodic_error.x_sin_deg"].note
    # its partner is not determined: held with it
    assert model.parameters["periodic_error.x_cos_deg"].fixed
    with pytest.raises(NotAdoptable, match="2 phases"):
        adopted_model(
            cols, ["periodic_error"], "ref", BENCH, "test", {"what": "a test"}, worm_axes=["x"]
        )


@pytest.mark.parametrize(
    "quad,zk,sk,rate",
    [
        (4e-4, 0.0, 0.0, 0.0),
        (-3e-4, 0.008, 2e-4, 0.0),
        (0.0, 0.0, 0.0, 0.25),
        (5e-4, -0.004, -3e-4, -0.1),
    ],
)
def test_the_reference_reading_model_is_inverted_exactly(quad, zk, sk, rate):
    rng = np.random.default_rng(7)
    truth = rng.uniform(-14, 14, 200)
    temp = rng.uniform(15, 28, 200)
    t_s = 1.8e9 + rng.uniform(0, 7200, 200)
    errors = reference.ReferenceErrors(
        ("sensor_nonlinearity", "temperature_drift", "time_drift"),
        (quad, quad),
        (zk, zk),
        sk,
        (rate, rate),
        20.0,
        1.8e9,
    )
    raw = apply_reading_errors(
        truth,
        quad_per_deg=quad,
        temp_delta_k=temp - 20.0,
        zero_per_k=zk,
        scale_per_k=sk,
        drift_deg=rate * (t_s - 1.8e9) / 3600.0,
    )
    x, y = reference.true_reading(errors, raw, raw, temp, t_s)
    np.testing.assert_allclose(x, truth, atol=1e-10)
    np.testing.assert_allclose(y, truth, atol=1e-10)
    missing_temp = reference.true_reading(errors, raw, raw, None, t_s)[0]
    assert np.isnan(missing_temp).all()
    assert "temperature" in reference.needs_note(errors, False, True)


def test_the_measurement_sensor_is_fitted_against_the_reference_without_its_errors():
    cols = columns(
        {"sensor_nonlinearity": {"ref_x_per_deg": 4e-4, "ref_y_per_deg": -3e-4}},
        np.linspace(-8, 8, 9),
        np.linspace(-8, 8, 9),
    )
    plain = KINEMATIC.fit(cols, FitOptions(extra={"bench": BENCH}))
    adopted = KINEMATIC.fit(
        cols, FitOptions(extra={"bench": BENCH, "effects": ["sensor_nonlinearity"]})
    )
    assert plain.state.get("reference_errors") is None
    assert adopted.state["reference_errors"]["effects"] == ["sensor_nonlinearity"]
    # noise-free readings of the measurement sensor at poses between the grid points, against the
    # true tilt
    fx = EffectSet.from_mapping(
        "stage",
        scenario(
            "180-360", {"sensor_nonlinearity": {"ref_x_per_deg": 4e-4, "ref_y_per_deg": -3e-4}}
        )["effects"],
    )
    x, y = np.meshgrid(np.linspace(-7, 7, 8), np.linspace(-7, 7, 8))
    sim = simulate_stage(BENCH, fx, x.ravel(), y.ravel(), 1.0, 1.0)
    meas = {"meas_x_deg": sim["meas_x_deg"], "meas_y_deg": sim["meas_y_deg"]}

    def error(model):
        out = KINEMATIC.correct(model, meas)
        return float(
            np.mean(
                np.hypot(
                    out["tilt_x_deg"] - sim["tilt_x_deg"], out["tilt_y_deg"] - sim["tilt_y_deg"]
                )
            )
        )

    assert error(adopted) < 0.2 * error(plain), (error(plain), error(adopted))


def test_the_plan_measures_what_the_points_cannot_test():
    cols = columns(
        {"periodic_error": {"x_amp_deg": 0.010, "x_phase_deg": 40.0}},
        np.linspace(-6, 6, 13),
        np.linspace(-6, 6, 5),
    )
    data = StageData.from_columns(cols, "ref", BENCH)
    report = {
        "skipped": [
            {"effect": "backlash", "reason": "a single approach direction per stage"},
            {"effect": "temperature_drift", "reason": "temperature constant"},
        ],
        "named_effects": ["periodic_error"],
    }
    needs = needs_of(report, {"periodic_error": ("x_cos_deg",)}, [], 0.25, data)
    assert {n.effect for n in needs} == {
        "backlash",
        "temperature_drift",
        "periodic_error",
        "time_drift",
    }
    plan = plan_measurement(data, BENCH, BENCH.travel_deg, needs, 12.0, "a test")
    doc = plan.as_dict()
    parts = {(p["effect"], p["measurement"][:40]): p for p in doc["parts"]}
    backlash = next(p for k, p in parts.items() if k[0] == "backlash")
    assert {(q[2], q[3]) for q in backlash["points"]} == {(-1.0, -1.0), (1.0, 1.0)} and backlash[
        "n_points"
    ] == 10
    scans = [p for k, p in parts.items() if k[0] == "periodic_error"]
    assert len(scans) == 2  # x (seen at two phases) and y (one phase): a period in eighths each
    x_scan = next(p for p in scans if "x stage" in p["measurement"])
    assert np.allclose(
        np.diff([q[0] for q in x_scan["points"]]),
        BENCH.worm_period_x_deg / 8,
        atol=BENCH.pulse_x_deg,
    )
    # the backlash part serves
    assert next(p for k, p in parts.items() if k[0] == "time_drift")["n_points"] == 0
    assert [c["effect"] for c in doc["cannot"]] == ["temperature_drift"]
    assert doc["n_points"] == 10 + 9 + 9 and doc["estimated_bench_s"] == pytest.approx(
        12.0 * doc["n_points"]
    )
    travel = BENCH.travel_deg
    assert all(
        abs(q["stage_x_deg"]) < travel and abs(q["stage_y_deg"]) < travel for q in doc["points"]
    )
    assert plan_measurement(data, BENCH, travel, [], 12.0, "a test").as_dict()["n_points"] == 0
    assert (
        "nothing to measure"
        in plan_measurement(data, BENCH, travel, [], 12.0, "").as_dict()["summary"]
    )


def test_the_adopted_effects_stated_uncertainties_cover_the_truth():
    """Over 30 simulated benches each: the worm's amplitude and phase (propagated from the
    sine/cosine pair's covariance) and the reference's quadratic coefficient lie within two stated
    standard uncertainties of the simulator's values about 95 % of the time, and the uncertainties
    are not inflated (median |z| near 0.67)."""
    z: dict[str, list[float]] = {"amplitude": [], "phase": [], "quadratic": []}
    for seed in range(30):
        rng = np.random.default_rng(1000 + seed)
        phase = float(rng.uniform(-180, 180))
        cols = columns(
            {"periodic_error": {"x_amp_deg": 0.010, "x_phase_deg": phase}},
            np.linspace(-9, 9, 31),
            np.linspace(-6, 6, 4),
            seed=seed,
        )
        worm = KINEMATIC.fit(
            cols,
            FitOptions(extra={"bench": BENCH, "effects": ["periodic_error"], "worm_axes": ["x"]}),
        ).fit["periodic_error"]["x"]
        z["amplitude"].append((worm["amplitude_deg"] - 0.010) / worm["u_amplitude_deg"])
        z["phase"].append(((worm["phase_deg"] - phase + 180) % 360 - 180) / worm["u_phase_deg"])
        quad = float(rng.uniform(2e-4, 5e-4))
        cols = columns(
            {"sensor_nonlinearity": {"ref_x_per_deg": quad}},
            np.linspace(-8, 8, 9),
            np.linspace(-8, 8, 9),
            seed=seed,
        )
        model = KINEMATIC.fit(
            cols, FitOptions(extra={"bench": BENCH, "effects": ["sensor_nonlinearity"]})
        )
        z["quadratic"].append(
            (model.value("sensor_nonlinearity.ref_x_per_deg") - quad)
            / model.std("sensor_nonlinearity.ref_x_per_deg")
        )
    for name, values in z.items():
        a = np.abs(values)
        assert np.mean(a <= 2.0) >= 0.85, (name, sorted(a))
        assert 0.4 <= np.median(a) <= 1.0, (name, np.median(a))


def test_a_drift_read_far_beyond_its_fitted_span_is_said_to_be_extrapolated():
    errors = reference.ReferenceErrors(
        ("time_drift",), (0.0, 0.0), (0.0, 0.0), 0.0, (0.1, 0.0), 20.0, 1.8e9, 600.0
    )
    assert reference.extrapolation_note(errors, 1.8e9 + 900.0) is None
    assert "600 s" in reference.extrapolation_note(errors, 1.8e9 + 5000.0)
    no_drift = reference.ReferenceErrors(
        ("sensor_nonlinearity",), (1e-4, 0.0), (0.0, 0.0), 0.0, (0.0, 0.0), 20.0, None
    )
    assert reference.extrapolation_note(no_drift, 1.8e9 + 5e6) is None
