"""The measurement sensor's batched frame and inverse against the plain matrix forms they replace in
the hot path.

meas_inverse_gum evaluates every perturbed case of its uncertainty in one batched call; these tests
hold it to a straightforward evaluation through meas_inverse, one perturbation at a time, and hold
the written-out frame and inverse to the 3x3 matrices of service.physics.rotations.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.calibration.differences import fd_step
from service.calibration.methods.stage.common import (
    meas_axes,
    meas_axes_batch,
    meas_forward,
    meas_inverse,
    meas_inverse_batch,
    meas_inverse_gum,
)
from service.calibration.uncertainty import welch_satterthwaite
from service.physics.rotations import plane_tilt, rz

# zero, zero, scale, scale, yaw, ν, seat x, seat y
SPREAD = np.array([0.5, 0.5, 0.01, 0.01, 3.0, 3.0, 3.0, 3.0])
SIGNS = [np.array(s) for s in ((1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0))]
seeds = st.integers(min_value=0, max_value=2**32 - 1)


def _params(rng, spread=SPREAD):
    return rng.normal(0.0, 1.0, 8) * spread


def _covariance(rng, zero_rows=()):
    """A random positive-definite covariance, strongly correlated like a real fit's, with some rows
    zero (held parameters)."""
    a = rng.normal(size=(8, 8)) * (0.1 * SPREAD)[:, None]
    cov = a @ a.T + np.diag((0.01 * SPREAD) ** 2)
    for i in zero_rows:
        cov[i, :] = 0.0
        cov[:, i] = 0.0
    return cov


def _readings(rng, p, sign, n):
    """Readings the sensor gives at table tilts within ±15°."""
    return meas_forward(p, sign, rng.uniform(-15, 15, n), rng.uniform(-15, 15, n))


def _matrix_inverse(p, sign, a, b):
    """The closed-form inverse in its 3x3 matrix form: Gram matrix inverted by LAPACK, numpy's cross
    product."""
    k = np.pi / 180.0
    ra = -np.sin((sign[0] * k / (1.0 + p[2])) * (np.asarray(a) - p[0]))
    rb = -np.sin((sign[1] * k / (1.0 + p[3])) * (np.asarray(b) - p[1]))
    m = meas_axes(p)
    Gi = np.linalg.inv(m @ m.T)
    c1 = Gi[0, 0] * ra + Gi[0, 1] * rb
    c2 = Gi[1, 0] * ra + Gi[1, 1] * rb
    w = np.cross(m[0], m[1])
    w = w / np.linalg.norm(w)
    if w[2] < 0:
        w = -w
    t = np.sqrt(np.clip(1.0 - (c1 * ra + c2 * rb), 0.0, None))
    nx = c1 * m[0, 0] + c2 * m[1, 0] + t * w[0]
    ny = c1 * m[0, 1] + c2 * m[1, 1] + t * w[1]
    return np.degrees(np.arcsin(np.clip(-nx, -1.0, 1.0))), np.degrees(
        np.arcsin(np.clip(-ny, -1.0, 1.0))
    )


def _gum_per_perturbation(p, cov, sign, a, b, sigma_deg, dof):
    """meas_inverse_gum's law evaluated plainly: meas_inverse once per perturbation, einsum for
    J·cov·Jᵀ."""
    X, Y = meas_inverse(p, sign, a, b)
    ha, hb = fd_step(a, 1.0), fd_step(b, 1.0)
    xp, yp = meas_inverse(p, sign, a + ha, b)
    xm, ym = meas_inverse(p, sign, a - ha, b)
    dXa, dYa = (xp - xm) / (2 * ha), (yp - ym) / (2 * ha)
    xp, yp = meas_inverse(p, sign, a, b + hb)
    xm, ym = meas_inverse(p, sign, a, b - hb)
    dXb, dYb = (xp - xm) / (2 * hb), (yp - ym) / (2 * hb)
    parts_x = [((sigma_deg * dXa) ** 2, dof), ((sigma_deg * dXb) ** 2, dof)]
    parts_y = [((sigma_deg * dYa) ** 2, dof), ((sigma_deg * dYb) ** 2, dof)]
    if cov is not None and np.any(cov):
        ka = -(a - p[0]) / (1.0 + p[2])
        kb = -(b - p[1]) / (1.0 + p[3])
        jx, jy = [-dXa, -dXb, dXa * ka, dXb * kb], [-dYa, -dYb, dYa * ka, dYb * kb]
        for i in range(4, p.size):
            if not np.any(cov[i]):
                jx.append(np.zeros_like(a))
                jy.append(np.zeros_like(a))
                continue
            h = float(fd_step(p[i], 1.0))
            pp, pm = p.copy(), p.copy()
            pp[i] += h
            pm[i] -= h
            xp, yp = meas_inverse(pp, sign, a, b)
            xm, ym = meas_inverse(pm, sign, a, b)
            jx.append((xp - xm) / (2 * h))
            jy.append((yp - ym) / (2 * h))
        Jx, Jy = np.stack(jx, axis=-1), np.stack(jy, axis=-1)
        parts_x.append((np.einsum("ni,ij,nj->n", Jx, cov, Jx), dof))
        parts_y.append((np.einsum("ni,ij,nj->n", Jy, cov, Jy), dof))
    ux, uy = np.sqrt(sum(v for v, _ in parts_x)), np.sqrt(sum(v for v, _ in parts_y))
    return X, Y, ux, uy, welch_satterthwaite(parts_x), welch_satterthwaite(parts_y)


@settings(max_examples=200, deadline=None)
@given(seeds, st.sampled_from([1.0, 30.0]))
def test_batched_axes_are_meas_axes_and_the_rotation_chain(seed, scale):
    rng = np.random.default_rng(seed)
    P = np.stack([_params(rng, SPREAD * scale) for _ in range(5)])
    axes = meas_axes_batch(P)
    assert axes.shape == (5, 2, 3)
    for p, m in zip(P, axes):
        np.testing.assert_allclose(m, meas_axes(p), rtol=0, atol=1e-15)
        yaw, nu, tx, ty = np.radians(p[4:8])
        base = np.array([[1.0, 0.0, 0.0], [-np.sin(nu), np.cos(nu), 0.0]])
        chain = (plane_tilt(tx, ty) @ rz(yaw) @ base.T).T  # seat tilt · yaw · base
        np.testing.assert_allclose(m, chain, rtol=0, atol=1e-15)
        # what the solve takes in closed form: the Gram matrix and the axes' cross product
        np.testing.assert_allclose(
            m @ m.T, [[1.0, -np.sin(nu)], [-np.sin(nu), 1.0]], rtol=0, atol=1e-15
        )
        np.testing.assert_allclose(
            np.cross(m[0], m[1]), np.cos(nu) * plane_tilt(tx, ty)[:, 2], rtol=0, atol=1e-15
        )


@settings(max_examples=200, deadline=None)
@given(seeds, st.sampled_from(range(4)))
def test_meas_inverse_matches_the_matrix_form_and_inverts_the_forward_model(seed, s):
    rng = np.random.default_rng(seed)
    p, sign = _params(rng), SIGNS[s]
    tx, ty = rng.uniform(-15, 15, 50), rng.uniform(-15, 15, 50)
    a, b = meas_forward(p, sign, tx, ty)
    X, Y = meas_inverse(p, sign, a, b)
    Xm, Ym = _matrix_inverse(p, sign, a, b)
    np.testing.assert_allclose(X, Xm, rtol=0, atol=1e-12)
    np.testing.assert_allclose(Y, Ym, rtol=0, atol=1e-12)
    np.testing.assert_allclose(X, tx, rtol=0, atol=1e-10)
    np.testing.assert_allclose(Y, ty, rtol=0, atol=1e-10)


@settings(max_examples=50, deadline=None)
@given(seeds, st.sampled_from(range(4)))
def test_meas_inverse_batch_reads_row_k_through_parameter_set_k(seed, s):
    rng = np.random.default_rng(seed)
    sign = SIGNS[s]
    P = np.stack([_params(rng) for _ in range(4)])
    A, B = (
        np.stack([_readings(rng, p, sign, 7)[0] for p in P]),
        np.stack([_readings(rng, p, sign, 7)[1] for p in P]),
    )
    X, Y = meas_inverse_batch(P, sign, A, B)
    assert X.shape == Y.shape == (4, 7)
    for k in range(4):
        Xk, Yk = meas_inverse(P[k], sign, A[k], B[k])
        np.testing.assert_allclose(X[k], Xk, rtol=1e-15, atol=1e-15)
        np.testing.assert_allclose(Y[k], Yk, rtol=1e-15, atol=1e-15)


COVARIANCES = ["full", "held yaw and seat y", "held scales", "all stepped held", "none", "zero"]


@settings(max_examples=150, deadline=None)
@given(
    seeds,
    st.sampled_from(range(4)),
    st.sampled_from(COVARIANCES),
    st.sampled_from([1, 3, 400]),
    st.sampled_from([np.inf, 12.0]),
)
def test_gum_in_one_batch_equals_one_meas_inverse_per_perturbation(seed, s, which, n, dof):
    """400 readings take the one-case-at-a-time path (13 cases x 400 above the batched size), 1 and
    3 the batched one."""
    rng = np.random.default_rng(seed)
    p, sign = _params(rng), SIGNS[s]
    zero_rows = {
        "full": (),
        "held yaw and seat y": (4, 7),
        "held scales": (2, 3),
        "all stepped held": (4, 5, 6, 7),
    }
    cov = {"none": None, "zero": np.zeros((8, 8))}.get(which)
    if which in zero_rows:
        cov = _covariance(rng, zero_rows[which])
    a, b = _readings(rng, p, sign, n)
    sigma = float(rng.uniform(1e-4, 1e-2))
    X, Y, gx, gy = meas_inverse_gum(p, cov, sign, a, b, sigma, dof)
    Xr, Yr, uxr, uyr, nuxr, nuyr = _gum_per_perturbation(p, cov, sign, a, b, sigma, dof)
    for got, want in (
        (X, Xr),
        (Y, Yr),
        (gx.u, uxr),
        (gy.u, uyr),
        (gx.dof_eff, nuxr),
        (gy.dof_eff, nuyr),
    ):
        assert got.shape == (n,)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)


def test_gum_keeps_the_readings_shape_and_broadcasts_a_constant_axis():
    rng = np.random.default_rng(7)
    p, sign = _params(rng), SIGNS[1]
    cov = _covariance(rng, (5,))
    a, b = _readings(rng, p, sign, 6)
    X, Y, gx, gy = meas_inverse_gum(p, cov, sign, a.reshape(2, 3), b.reshape(2, 3), 1e-3, 20.0)
    flat = meas_inverse_gum(p, cov, sign, a, b, 1e-3, 20.0)
    for got, want in ((X, flat[0]), (Y, flat[1]), (gx.u, flat[2].u), (gy.dof_eff, flat[3].dof_eff)):
        assert got.shape == (2, 3)
        np.testing.assert_array_equal(got.ravel(), want)
    Xc, _, gxc, _ = meas_inverse_gum(p, cov, sign, a, float(b[0]), 1e-3, 20.0)
    Xf, _, gxf, _ = meas_inverse_gum(p, cov, sign, a, np.full(6, b[0]), 1e-3, 20.0)
    np.testing.assert_array_equal(Xc, Xf)
    np.testing.assert_array_equal(gxc.u, gxf.u)


@pytest.mark.parametrize("s", range(4))
def test_one_reading_equals_the_same_reading_among_many(s):
    """The daemon corrects one reading at a time: the batched single-reading path gives what a bulk
    call gives it."""
    rng = np.random.default_rng(11 + s)
    p, sign = _params(rng), SIGNS[s]
    cov = _covariance(rng, (6,))
    a, b = _readings(rng, p, sign, 500)
    bulk = meas_inverse_gum(p, cov, sign, a, b, 2e-3, 40.0)
    for i in (0, 123, 499):
        one = meas_inverse_gum(p, cov, sign, a[i : i + 1], b[i : i + 1], 2e-3, 40.0)
        np.testing.assert_allclose(one[0], bulk[0][i], rtol=1e-15, atol=0)
        np.testing.assert_allclose(one[2].u, bulk[2].u[i], rtol=1e-12, atol=0)
        np.testing.assert_allclose(one[3].dof_eff, bulk[3].dof_eff[i], rtol=1e-12, atol=0)
