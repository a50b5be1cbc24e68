"""Stage calibration building blocks pinned to seed 000 and to independent derivations."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.calibration.methods.stage.common import (
    meas_forward,
    meas_inverse,
    offaxis_forward_vs_exact_deg,
    offaxis_paper_forward_deg,
)
from service.calibration.projective import apply_projective, fit_projective
from service.errors import DegenerateDataError
from service.physics import stage as physics_stage
from service.physics.effects import EffectSet
from service.physics.stage import (
    StageBench,
    StageGeometry,
    offaxis_error_deg,
    offaxis_inverse_deg,
    offaxis_reading_deg,
    simulate_stage,
)

angle12 = st.floats(min_value=-12.0, max_value=12.0, allow_nan=False)
angle15 = st.floats(min_value=-15.0, max_value=15.0, allow_nan=False)


def _eq10_as_printed(tx_deg, ty_deg):
    """Seed 000 eq. (10) in the paper's own two-branch atan/sqrt form."""
    tx, ty = np.radians(tx_deg), np.radians(ty_deg)
    q = np.sin(tx) ** 2 * np.cos(ty) ** 2
    r = np.arctan(np.sqrt(q / (1.0 - q)))
    return np.degrees(tx - r) if tx >= 0 else np.degrees(tx + r)


@settings(max_examples=300, deadline=None)
@given(angle15, angle15)
def test_eq10_error_is_theta_x_minus_asin_sin_cos(tx, ty):
    want = tx - np.degrees(np.arcsin(np.sin(np.radians(tx)) * np.cos(np.radians(ty))))
    assert abs(offaxis_error_deg(tx, ty) - want) < 1e-10
    assert abs(_eq10_as_printed(tx, ty) - want) < 1e-10
    assert abs(physics_stage.offaxis_error_deg(tx, ty) - want) < 1e-10


@settings(max_examples=300, deadline=None)
@given(angle12, angle12)
def test_exact_inverse_inverts_the_forward_model(x_wanted, y):
    x_cmd = offaxis_inverse_deg(x_wanted, y)
    assert abs(offaxis_reading_deg(x_cmd, y) - x_wanted) < 1e-10
    # and the simulator's ideal geometry (commands not rounded to pulses) then reads the wanted x
    geo = StageGeometry.from_effects(StageBench(), EffectSet.from_mapping("stage", {}))
    r = geo.readings_deg(np.radians(np.atleast_1d(x_cmd)), np.radians([y]))
    assert abs(r["tilt_x"][0] - x_wanted) < 1e-9 and abs(r["tilt_y"][0] - y) < 1e-9


def test_paper_forward_form_vs_exact_inverse_on_the_12_deg_grid():
    """x' + error(x', y) agrees with the exact inverse to second order in the angles; the rest is
    0.0062 deg at the corners."""
    d = offaxis_forward_vs_exact_deg()
    # independent arithmetic at the corner (12, 12)
    s12, c12 = np.sin(np.radians(12.0)), np.cos(np.radians(12.0))
    exact = np.degrees(np.arcsin(s12 / c12))
    forward = 12.0 + (12.0 - np.degrees(np.arcsin(s12 * c12)))
    assert abs(d["max_abs_command_difference_deg"] - abs(exact - forward)) < 1e-12
    assert 0.006 < d["max_abs_command_difference_deg"] < 0.0065
    assert abs(abs(d["at_x_deg"]) - 12) < 1e-12 and abs(abs(d["at_y_deg"]) - 12) < 1e-12
    # on the axes both forms agree exactly (eq. 10's error vanishes there)
    assert offaxis_paper_forward_deg(7.0, 0.0) == offaxis_inverse_deg(7.0, 0.0) == 7.0


def test_dlt_recovers_a_known_homography_exactly():
    H = np.array([[1.003, 0.012, -0.21], [-0.008, 0.997, 0.06], [2e-4, -1e-4, 1.0]])
    g = np.arange(-12.0, 12.1, 3.0)
    X, Y = (a.ravel() for a in np.meshgrid(g, g))
    x, y = apply_projective(H, X, Y)
    for refine in (False, True):
        Hf = fit_projective(X, Y, x, y, refine=refine)
        assert np.allclose(Hf, H, rtol=0, atol=1e-10)
    # four points are enough (seed 000 §3)
    Hf = fit_projective(X[[0, 8, 72, 80]], Y[[0, 8, 72, 80]], x[[0, 8, 72, 80]], y[[0, 8, 72, 80]])
    assert np.allclose(Hf, H, rtol=0, atol=1e-10)


def _meas_only_bench(flip, yaw, nonorth, seat_x, seat_y, zx, zy, kx, ky):
    fx = EffectSet.from_mapping(
        "stage",
        {
            "sensor_yaw": {"meas_deg": yaw},
            "non_orthogonality": {"meas_deg": nonorth},
            "mounting_tilt": {"meas_x_deg": seat_x, "meas_y_deg": seat_y},
            "zero_offset": {"meas_x_deg": zx, "meas_y_deg": zy},
            "scale_factor": {"meas_x": kx, "meas_y": ky},
        },
    )
    return StageBench(meas_flip=flip), fx


@settings(max_examples=60, deadline=None)
@given(
    st.sampled_from(["none", "x", "y"]),
    st.floats(-2, 2),
    st.floats(-1, 1),
    st.floats(-1, 1),
    st.floats(-1, 1),
    st.floats(-0.5, 0.5),
    st.floats(-0.5, 0.5),
    st.floats(-0.01, 0.01),
    st.floats(-0.01, 0.01),
)
def test_measurement_model_matches_the_simulator_and_inverts(
    flip, yaw, nonorth, sx, sy, zx, zy, kx, ky
):
    """The kinematic measurement model (reference frame) against the simulator's chain, with the
    upside-down mountings: turned about x mirrors y (and the sense of ν), about y mirrors x."""
    bench, fx = _meas_only_bench(flip, yaw, nonorth, sx, sy, zx, zy, kx, ky)
    g = np.arange(-12.0, 12.1, 4.0)
    cx, cy = (a.ravel() for a in np.meshgrid(g, g))
    sim = simulate_stage(bench, fx, cx, cy)
    sign = np.array({"none": (1, 1), "x": (1, -1), "y": (-1, 1)}[flip], dtype=float)
    nu = nonorth if flip == "none" else -nonorth
    p = np.array([zx, zy, kx, ky, yaw, nu, sx, sy])
    a, b = meas_forward(p, sign, sim["tilt_x_deg"], sim["tilt_y_deg"])
    assert np.allclose(a, sim["meas_x_deg"], atol=1e-9) and np.allclose(
        b, sim["meas_y_deg"], atol=1e-9
    )
    X, Y = meas_inverse(p, sign, sim["meas_x_deg"], sim["meas_y_deg"])
    assert np.allclose(X, sim["tilt_x_deg"], atol=1e-9) and np.allclose(
        Y, sim["tilt_y_deg"], atol=1e-9
    )


def test_four_points_with_three_on_one_line_do_not_determine_a_homography():
    """Three collinear points of four leave a one-parameter family of homographies: refused, not
    guessed."""
    x, y = np.array([0.0, 1.0, 2.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0])
    with pytest.raises(DegenerateDataError, match="do not determine a homography"):
        fit_projective(x + 0.02 * x * y, y + 0.003 * x, x, y)
