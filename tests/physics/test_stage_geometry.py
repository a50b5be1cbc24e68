"""The stacked-stage model against seed 000's own derivation (eqs. 4-10), written out
independently."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.physics.effects import EffectSet
from service.physics.stage import (
    StageBench,
    StageGeometry,
    offaxis_error_deg,
    offaxis_reading_deg,
    simulate_stage,
)

angle = st.floats(min_value=-15.0, max_value=15.0, allow_nan=False)


def _ideal_geometry():
    return StageGeometry.from_effects(StageBench(), EffectSet.from_mapping("stage", {}))


def _paper_chain(theta_x_deg, theta_y_deg):
    """Seed 000 eqs. (4) and (8): x0 = [1,0,0] turned about Y by θx, then about X by θy, matrices as
    printed."""
    tx, ty = np.radians(theta_x_deg), np.radians(theta_y_deg)
    ry_paper = np.array([[np.cos(tx), 0, np.sin(tx)], [0, 1, 0], [-np.sin(tx), 0, np.cos(tx)]])
    rx_paper = np.array([[1, 0, 0], [0, np.cos(ty), -np.sin(ty)], [0, np.sin(ty), np.cos(ty)]])
    return rx_paper @ ry_paper @ np.array([1.0, 0.0, 0.0])


@settings(max_examples=300, deadline=None)
@given(angle, angle)
def test_x_reading_is_seed000_eq9_and_the_chain_of_eq8(tx, ty):
    geo = _ideal_geometry()
    r = geo.readings_deg(np.radians([tx]), np.radians([ty]))
    # eq. (9): the angle of x0² to the horizontal, atan(sqrt(sin²θx cos²θy / (cos²θx + sin²θx
    # sin²θy)))
    v = _paper_chain(tx, ty)
    eq9 = np.sign(tx) * np.degrees(np.arctan(np.sqrt(v[2] ** 2 / (v[0] ** 2 + v[1] ** 2))))
    assert abs(r["ref_x"][0] - eq9) < 1e-9
    assert abs(r["ref_x"][0] - offaxis_reading_deg(tx, ty)) < 1e-9
    # eq. (10): error = θx - reading
    assert abs((tx - r["ref_x"][0]) - offaxis_error_deg(tx, ty)) < 1e-9
    # the lower stage's axis reads its own angle exactly (docs/models.md §2: y = θy)
    assert abs(r["ref_y"][0] - ty) < 1e-9


def test_offaxis_error_vanishes_on_the_axes_and_peaks_at_the_corners():
    """Seed 000 Fig. 6 and §3: near θx = 0 or θy = 0 the error is ~0 (why those points suit the
    homography)."""
    g = np.arange(-12, 13, 3.0)
    X, Y = np.meshgrid(g, g)
    e = offaxis_error_deg(X, Y)
    assert np.all(np.abs(e[:, g == 0]) < 1e-12) and np.all(np.abs(e[g == 0, :]) < 1e-12)
    assert np.isclose(np.max(np.abs(e)), np.max(np.abs(e[[0, 0, -1, -1], [0, -1, 0, -1]])))
    # odd in θx, even in θy
    assert np.allclose(e, -offaxis_error_deg(-X, Y)) and np.allclose(e, offaxis_error_deg(X, -Y))
    # at (12, 12): 12 - asin(sin 12° cos 12°) = 12 - 11.7340 = 0.2660 deg, a few tenths as seed 000
    # reports
    assert abs(offaxis_error_deg(12.0, 12.0) - 0.2660) < 1e-4


@settings(max_examples=100, deadline=None)
@given(angle, angle)
def test_decoupled_bench_reads_the_commanded_angles(tx, ty):
    """With coupling switched off (idealised bench) an ideal sensor reads exactly the stage
    angles."""
    geo = StageGeometry.from_effects(
        StageBench(), EffectSet.from_mapping("stage", {"offaxis_coupling": {"enabled": False}})
    )
    r = geo.readings_deg(np.radians([tx]), np.radians([ty]))
    assert abs(r["ref_x"][0] - tx) < 1e-9 and abs(r["ref_y"][0] - ty) < 1e-9


@settings(max_examples=100, deadline=None)
@given(angle, angle, st.floats(-3, 3), st.floats(-3, 3))
def test_desk_tilt_is_a_rotation_of_the_whole_bench(tx, ty, dx, dy):
    """A desk tilt composes with the stages as a rotation before them: checked with explicit
    matrices."""
    fx = EffectSet.from_mapping("stage", {"mounting_tilt": {"desk_x_deg": dx, "desk_y_deg": dy}})
    geo = StageGeometry.from_effects(StageBench(), fx)
    r = geo.readings_deg(np.radians([tx]), np.radians([ty]))

    def rxm(a):
        a = np.radians(a)
        return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])

    def rym(a):
        a = np.radians(a)
        return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])

    R = rxm(-dy) @ rym(dx) @ rxm(-ty) @ rym(tx)
    want_x = np.degrees(np.arcsin(-(R @ [1, 0, 0])[2]))
    want_y = np.degrees(np.arcsin(-(R @ [0, 1, 0])[2]))
    assert abs(r["ref_x"][0] - want_x) < 1e-9 and abs(r["ref_y"][0] - want_y) < 1e-9


def test_pulse_equivalents_are_seed000s_resolutions():
    b = StageBench()
    assert abs(b.pulse_x_deg - 0.000703125) < 1e-12  # 1.8 / (8 * 320): "0.0007 deg"
    assert abs(b.pulse_y_deg - 0.0005) < 1e-12  # 1.8 / (8 * 450)
    assert abs(b.worm_period_x_deg - 1.125) < 1e-12 and abs(b.worm_period_y_deg - 0.8) < 1e-12
    qx, qy = b.quantise([10.0], [10.0])
    assert (
        abs(qx[0] / b.pulse_x_deg - round(qx[0] / b.pulse_x_deg)) < 1e-9
        and abs(qx[0] - 10.0) <= b.pulse_x_deg / 2
    )


def test_upside_down_measurement_sensor_mirrors_one_axis():
    fx = EffectSet.from_mapping("stage", {})
    up = simulate_stage(StageBench(meas_flip="none"), fx, [5.0], [-7.0])
    down = simulate_stage(StageBench(meas_flip="x"), fx, [5.0], [-7.0])
    assert np.isclose(down["meas_x_deg"][0], up["meas_x_deg"][0]) and np.isclose(
        down["meas_y_deg"][0], -up["meas_y_deg"][0]
    )
    down_y = simulate_stage(StageBench(meas_flip="y"), fx, [5.0], [-7.0])
    assert np.isclose(down_y["meas_x_deg"][0], -up["meas_x_deg"][0]) and np.isclose(
        down_y["meas_y_deg"][0], up["meas_y_deg"][0]
    )
