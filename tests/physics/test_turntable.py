"""Seed 004's symmetric positions: the half-difference cancels the zero offsets."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.physics.effects import EffectSet
from service.physics.turntable import TurntableInclinometer, simulate_turntable, turntable_readings

f = st.floats


@settings(max_examples=300, deadline=None)
@given(
    f(-180, 180),
    f(-2, 2),
    f(0.5, 2),
    f(0.5, 2),
    f(0, 360),
    f(-100, 100),
    f(-100, 100),
    f(-10, 10),
    f(-10, 10),
)
def test_half_difference_cancels_zero_offsets(beta, eps, m1, m2, az, xi, eta, z1, z2):
    p = TurntableInclinometer(beta, eps, m1, m2)
    n1a, n2a = turntable_readings(p, az, xi, eta, z1, z2)
    n1b, n2b = turntable_readings(p, az + 180.0, xi, eta, z1, z2)
    h1, h2 = (n1a - n1b) / 2, (n2a - n2b) / 2
    ref1, ref2 = turntable_readings(p, az, xi, eta, 0.0, 0.0)
    assert abs(h1 - ref1) < 1e-9 * (1 + abs(ref1)) and abs(h2 - ref2) < 1e-9 * (1 + abs(ref2))
    # and the half-sum is the zero offset
    assert abs((n1a + n1b) / 2 - z1) < 1e-9 * (1 + abs(z1) + abs(ref1)) and abs(
        (n2a + n2b) / 2 - z2
    ) < 1e-9 * (1 + abs(z2) + abs(ref2))


def test_orthogonal_unit_inclinometer_reads_the_axis_tilt_in_its_own_frame():
    """β = 0, ε = 0, m = 1 at A = 0: n1 = ξ (north), n2 = η (east); at A = 90 the frame has
    turned."""
    p = TurntableInclinometer(0.0, 0.0, 1.0, 1.0)
    n1, n2 = turntable_readings(p, 0.0, 30.0, -12.0)
    assert np.isclose(n1, 30.0) and np.isclose(n2, -12.0)
    n1, n2 = turntable_readings(p, 90.0, 30.0, -12.0)
    assert np.isclose(n1, -12.0) and np.isclose(n2, -30.0)


@settings(max_examples=200, deadline=None)
@given(
    f(-180, 180), f(-1, 1), f(0.5, 2), f(0, 360), f(-100, 100), f(-100, 100), f(-5, 5), f(-10, 10)
)
def test_rotation_error_turns_beta_by_half_of_it(beta, eps, m1, az, xi, eta, dphi, z1):
    """Seed 004 §3.2: with φ = 180° + Δφ the half-difference is the φ = 180° one with β + Δφ/2,
    scaled by cos(Δφ/2): cos(a) + cos(a + Δ) = 2 cos(Δ/2) cos(a + Δ/2). So β and φ cannot be told
    apart from pairs."""
    p = TurntableInclinometer(beta, eps, m1, m1)
    fx = EffectSet.from_mapping("turntable", {"zero_offset": {"z1": z1, "z2": -z1}})
    off = simulate_turntable(p, fx, [az], xi, eta, rotation_deg=180.0 + dphi)
    h1 = (off["n1_a"] - off["n1_b"]) / 2
    h2 = (off["n2_a"] - off["n2_b"]) / 2
    shifted = TurntableInclinometer(
        beta + dphi / 2, eps, m1 * np.cos(np.radians(dphi / 2)), m1 * np.cos(np.radians(dphi / 2))
    )
    w1, w2 = turntable_readings(shifted, az, xi, eta)
    assert abs(h1[0] - w1) < 1e-9 * (1 + abs(w1)) and abs(h2[0] - w2) < 1e-9 * (1 + abs(w2))
