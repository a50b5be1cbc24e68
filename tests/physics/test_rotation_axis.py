"""Seed 002's rotation model: docs/models.md §3 outputs against an independent construction and eqs.
(6)-(10)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.physics.effects import EffectSet
from service.physics.rotation_axis import RotationBench, rotation_outputs, simulate_rotation

alpha = st.floats(-180, 180)
beta = st.floats(-89, 89)
gamma = st.floats(-45, 45)
theta = st.floats(-180, 180)


def _rodrigues(v, axis, t):
    return v * np.cos(t) + np.cross(axis, v) * np.sin(t) + axis * (axis @ v) * (1 - np.cos(t))


def _constructed(a_deg, b_deg, g_deg, t_deg):
    """Seed 002 §1.1 built from its words: L in the YOZ plane at β to the horizontal; at θ = 0 the
    sensor normal n0 lies in YOZ and the sensor plane makes γ with L; x makes α with X; the axes
    turn by θ about L. The outputs are the z components of the turned x, y axes and normal (sines of
    their angles to the horizontal)."""
    a, b, g, t = np.radians([a_deg, b_deg, g_deg, t_deg])
    L = np.array([0.0, np.cos(b), np.sin(b)])
    n0 = np.array([0.0, -np.sin(b + g), np.cos(b + g)])
    e1 = np.array([1.0, 0.0, 0.0])
    e2 = np.cross(n0, e1)
    cx0 = np.cos(a) * e1 + np.sin(a) * e2
    cy0 = -np.sin(a) * e1 + np.cos(a) * e2
    assert abs(np.degrees(np.arcsin(abs(L @ n0))) - abs(g_deg)) < 1e-6  # plane at γ to L
    assert np.allclose(np.cross(cx0, cy0), n0)  # z is x × y, the normal (seed 002 §2.1)
    return tuple(_rodrigues(v, L, t)[2] for v in (cx0, cy0, n0))


@settings(max_examples=300, deadline=None)
@given(alpha, beta, gamma, theta)
def test_outputs_equal_the_independent_construction(a, b, g, t):
    got = rotation_outputs(a, b, g, t)
    want = _constructed(a, b, g, t)
    assert np.allclose(got, want, atol=1e-12)


@settings(max_examples=300, deadline=None)
@given(alpha, beta, gamma, theta)
def test_identities_6_to_10_hold_for_any_geometry(a, b, g, t):
    sx, sy, sz = rotation_outputs(a, b, g, t)
    ar, br, gr, tr = np.radians([a, b, g, t])
    assert abs(sx**2 + sy**2 + sz**2 - 1.0) < 1e-12  # (6)
    assert abs(sx * np.cos(ar) - sy * np.sin(ar) + np.cos(br) * np.sin(tr)) < 1e-12  # (7)
    # (8)
    assert (
        abs(
            sx * np.sin(ar)
            + sy * np.cos(ar)
            - (np.cos(gr) * np.sin(br) + np.sin(gr) * np.cos(br) * np.cos(tr))
        )
        < 1e-12
    )
    # (10)
    assert (
        abs((sx * np.sin(ar) + sy * np.cos(ar)) * np.cos(gr) - sz * np.sin(gr) - np.sin(br)) < 1e-12
    )


@settings(max_examples=100, deadline=None)
@given(alpha, st.floats(-80, 80), st.floats(-30, 30))
def test_sensor_track_is_seed002s_ellipse(a, b, g):
    """§1.2: (Sx, Sy) runs on an ellipse centred at (sin α cos γ sin β, cos α cos γ sin β),
    semi-axes |cos β| and |cos β sin γ|."""
    t = np.linspace(-180, 180, 721)
    sx, sy, _ = rotation_outputs(a, b, g, t)
    ar, br, gr = np.radians([a, b, g])
    cx, cy = np.sin(ar) * np.cos(gr) * np.sin(br), np.cos(ar) * np.cos(gr) * np.sin(br)
    # coordinates along the two principal directions (rotated by α)
    u = (sx - cx) * np.cos(ar) - (sy - cy) * np.sin(ar)
    v = (sx - cx) * np.sin(ar) + (sy - cy) * np.cos(ar)
    assert np.isclose(np.max(np.abs(u)), abs(np.cos(br)), atol=1e-9)
    assert np.isclose(np.max(np.abs(v)), abs(np.cos(br) * np.sin(gr)), atol=1e-9)


def test_sine_domain_errors_grow_as_one_over_cos_in_angle():
    """Constant output noise means angle errors that grow with the axis tilt (seed 002 §2.1 (3),
    §4)."""
    fx = EffectSet.from_mapping("rotation", {"noise": {"sigma_s": 1e-4}})
    bench = RotationBench(0.0, 0.0, 0.0)  # y axis along L, horizontal: x axis tilts by θ
    rng = np.random.default_rng(7)
    errs = {}
    for t in (0.0, 60.0):
        out = simulate_rotation(bench, fx, np.full(20000, t), rng)
        errs[t] = np.std(np.degrees(np.arcsin(np.clip(out["sx"], -1, 1))) + t)
    assert 1.8 < errs[60.0] / errs[0.0] < 2.2  # 1 / cos 60 = 2
