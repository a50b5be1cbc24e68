"""Each effect, switched on alone, moves exactly the outputs it physically acts on (and nothing
else)."""

import re

import numpy as np
import pytest

from service.physics.effects import STAGE_EFFECTS, EffectSet
from service.physics.stage import StageBench, simulate_stage

READINGS = {"ref_x_deg", "ref_y_deg", "meas_x_deg", "meas_y_deg"}
TRUTH = {"tilt_x_deg", "tilt_y_deg"}
STAGE = {"actual_x_deg", "actual_y_deg"}
EVERYTHING_DOWNSTREAM = READINGS | TRUTH


def expected_outputs(effect: str, param: str) -> set[str]:
    """What a lab engineer would say each parameter moves; written from docs/models.md §2/§5, not
    read off the model."""
    sensor_axis = re.match(r"(ref|meas)_(x|y)", param)
    if effect in ("zero_offset", "scale_factor", "sensor_nonlinearity") or (
        effect in ("temperature_drift", "time_drift") and sensor_axis and "scale" not in param
    ):
        return {f"{sensor_axis.group(1)}_{sensor_axis.group(2)}_deg"}
    if effect == "temperature_drift":  # {s}_scale_per_k
        s = param.split("_")[0]
        return {f"{s}_x_deg", f"{s}_y_deg"}
    if effect == "non_orthogonality":  # the y axis turns; table tilt is defined on orthogonal axes
        return {f"{param.split('_')[0]}_y_deg"}
    if effect == "sensor_yaw":
        s = param.split("_")[0]
        return {f"{s}_x_deg", f"{s}_y_deg"} | (TRUTH if s == "ref" else set())
    if effect == "mounting_tilt":
        # A plane above the stages tilted about Y (x part) leaves a y axis where it was (Ry e_y =
        # e_y), and tilted about X (y part) leaves an x axis where it was: first-order separable,
        # exactly. The desk sits under both stages, so its tilt reaches every reading.
        plane, ax = param.split("_")[0], param.split("_")[1]
        sensors = {"meas": ("meas",), "ref": ("ref", "tilt"), "top": ("ref", "meas", "tilt")}.get(
            plane
        )
        if sensors is None:
            return EVERYTHING_DOWNSTREAM
        return {f"{s}_{ax}_deg" for s in sensors}
    if effect == "axis_misalignment":
        return EVERYTHING_DOWNSTREAM
    if effect in ("stage_scale", "backlash", "periodic_error"):
        if param.endswith("phase_deg"):
            return set()  # a phase with no amplitude is no error
        ax = param[0]
        if ax == "x":  # the upper stage turns about Y: y readings cannot see it
            return {"actual_x_deg", "ref_x_deg", "meas_x_deg", "tilt_x_deg"}
        # the lower stage carries the upper: x couples
        return {"actual_y_deg"} | EVERYTHING_DOWNSTREAM
    if effect == "offaxis_coupling":
        return {"ref_x_deg", "meas_x_deg", "tilt_x_deg"}  # only the upper stage's readings couple
    if effect == "settling":
        # a transient after a move: a static pose never sees it (tests/physics/test_settling.py)
        return set()
    raise AssertionError(f"no expectation written for {effect}.{param}")


CASES = [
    (e.name, p.name)
    for e in STAGE_EFFECTS.values()
    for p in e.params
    if e.name not in ("noise",) and p.name != "random_walk_deg_per_sqrt_h"
]


def _grid():
    g = np.arange(-12, 13, 3.0)
    x, y = np.meshgrid(g, g)
    x, y = x.ravel(), y.ravel()
    d = np.where(np.arange(x.size) % 2, 1.0, -1.0)
    return x, y, d, -d, 20.0 + np.linspace(-3, 3, x.size), np.linspace(0, 7200, x.size)


@pytest.mark.parametrize("effect,param", CASES, ids=[f"{e}.{p}" for e, p in CASES])
def test_effect_moves_only_its_outputs(effect, param):
    p = STAGE_EFFECTS[effect].param(param)
    bench = StageBench()
    x, y, dx, dy, temp, t = _grid()
    if effect == "offaxis_coupling":
        base = EffectSet.from_mapping("stage", {})
        on = EffectSet.from_mapping("stage", {"offaxis_coupling": {"enabled": False}})
    else:
        base = EffectSet.from_mapping("stage", {})
        on = EffectSet.from_mapping(
            "stage", {effect: {param: p.lo + 0.3 * (p.hi - p.lo) if p.lo < 0 else 0.3 * p.hi}}
        )
    a = simulate_stage(bench, base, x, y, dx, dy, temp, t)
    b = simulate_stage(bench, on, x, y, dx, dy, temp, t)
    moved = {k for k in a if np.max(np.abs(a[k] - b[k])) > 1e-9}
    assert moved == expected_outputs(effect, param)


def test_zero_offset_moves_its_reading_by_exactly_the_offset():
    x, y, dx, dy, temp, t = _grid()
    a = simulate_stage(StageBench(), EffectSet.from_mapping("stage", {}), x, y, dx, dy, temp, t)
    b = simulate_stage(
        StageBench(),
        EffectSet.from_mapping("stage", {"zero_offset": {"meas_y_deg": 0.0123}}),
        x,
        y,
        dx,
        dy,
        temp,
        t,
    )
    assert np.allclose(b["meas_y_deg"] - a["meas_y_deg"], 0.0123, atol=1e-12)


def test_backlash_is_half_the_width_against_the_last_move():
    x, y, dx, dy, temp, t = _grid()
    b = simulate_stage(
        StageBench(),
        EffectSet.from_mapping("stage", {"backlash": {"x_deg": 0.02}}),
        x,
        y,
        dx,
        dy,
        temp,
        t,
    )
    a = simulate_stage(StageBench(), EffectSet.from_mapping("stage", {}), x, y, dx, dy, temp, t)
    assert np.allclose(b["actual_x_deg"] - a["actual_x_deg"], -dx * 0.01, atol=1e-12)


def test_periodic_error_repeats_every_worm_turn():
    bench = StageBench()
    fx = EffectSet.from_mapping("stage", {"periodic_error": {"x_amp_deg": 0.01, "x_phase_deg": 30}})
    base = EffectSet.from_mapping("stage", {})
    x = np.array([1.0, 1.0 + bench.worm_period_x_deg, 1.0 + 2 * bench.worm_period_x_deg])
    e = (
        simulate_stage(bench, fx, x, 0 * x)["actual_x_deg"]
        - simulate_stage(bench, base, x, 0 * x)["actual_x_deg"]
    )
    # equal up to pulse quantisation of the period
    assert np.allclose(e, e[0], atol=2e-6) and abs(e[0]) > 1e-3


@pytest.mark.parametrize(
    "param,columns",
    [
        ("ref_sigma_deg", {"ref_x_deg", "ref_y_deg"}),
        ("meas_sigma_deg", {"meas_x_deg", "meas_y_deg"}),
        ("stage_sigma_deg", STAGE | EVERYTHING_DOWNSTREAM),
    ],
)
def test_noise_reaches_only_its_outputs(param, columns):
    x, y, dx, dy, temp, t = _grid()
    fx = EffectSet.from_mapping("stage", {"noise": {param: 0.01}})
    clean = simulate_stage(StageBench(), fx, x, y, dx, dy, temp, t)
    noisy = simulate_stage(StageBench(), fx, x, y, dx, dy, temp, t, rng=np.random.default_rng(3))
    moved = {k for k in clean if np.max(np.abs(clean[k] - noisy[k])) > 1e-9}
    assert moved == columns
