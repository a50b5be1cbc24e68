"""The homography fit against a plain reference kept here: the refinement as it was before the fit
formed its normal equations directly (Levenberg-Marquardt on the Jacobian matrix written column by
column, np.linalg.solve), after a DLT derived independently (the SVD of A built point by point). The
fit in service/ must give the same homography to 1e-10, entry by entry."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from service.calibration.projective import (
    REFINE_COST_TOL,
    REFINE_MAX_ITERATIONS,
    REFINE_STEP_TOL,
    apply_projective,
    fit_projective,
    transfer_residuals,
)

Array = NDArray[np.float64]


def _reference_transfer(
    h8: Array, sx: Array, sy: Array, dx: Array, dy: Array
) -> tuple[Array, Array]:
    """Residuals [H·src - dst in x; in y] and the Jacobian (2n x 8), column by column."""
    w_inv = 1.0 / (h8[6] * sx + h8[7] * sy + 1.0)
    px = (h8[0] * sx + h8[1] * sy + h8[2]) * w_inv
    py = (h8[3] * sx + h8[4] * sy + h8[5]) * w_inv
    n = sx.size
    J = np.zeros((2 * n, 8))
    J[:n, 0] = J[n:, 3] = sx * w_inv
    J[:n, 1] = J[n:, 4] = sy * w_inv
    J[:n, 2] = J[n:, 5] = w_inv
    J[:n, 6] = -px * J[:n, 0]
    J[:n, 7] = -px * J[:n, 1]
    J[n:, 6] = -py * J[:n, 0]
    J[n:, 7] = -py * J[:n, 1]
    return np.concatenate([px - dx, py - dy]), J


def _reference_refine(h: Array, sx: Array, sy: Array, dx: Array, dy: Array) -> Array:
    r, J = _reference_transfer(h, sx, sy, dx, dy)
    cost = float(r @ r)
    damping = 0.0
    norms = np.sqrt(np.einsum("ij,ij->j", J, J))
    norms[norms == 0] = 1.0
    for _ in range(REFINE_MAX_ITERATIONS):
        Js = J / norms
        N = Js.T @ Js
        if damping:
            N = N + damping * np.diag(np.diag(N))
        step = -np.linalg.solve(N, Js.T @ r) / norms
        trial = h + step
        r_new, J_new = _reference_transfer(trial, sx, sy, dx, dy)
        cost_new = float(r_new @ r_new)
        if not cost_new <= cost * (1.0 + REFINE_COST_TOL):
            damping = max(10.0 * damping, 1e-6)
            if damping > 1e12:
                break
            continue
        if cost - cost_new <= REFINE_COST_TOL * cost or np.all(
            np.abs(step) <= REFINE_STEP_TOL * (np.abs(h) + REFINE_STEP_TOL)
        ):
            return trial
        h, r, cost, J = trial, r_new, cost_new, J_new
        damping *= 0.1
    return h


def _reference_fit(sx: Array, sy: Array, dx: Array, dy: Array, refine: bool = True) -> Array:
    """Hartley-normalised DLT (null vector of A by SVD, A built row by row) and the refinement."""

    def normaliser(x: Array, y: Array) -> Array:
        cx, cy = x.mean(), y.mean()
        s = np.sqrt(2.0) / np.mean(np.sqrt((x - cx) ** 2 + (y - cy) ** 2))
        return np.array([[s, 0.0, -s * cx], [0.0, s, -s * cy], [0.0, 0.0, 1.0]])

    Ts, Td = normaliser(sx, sy), normaliser(dx, dy)
    rows = []
    for x, y, u, v in zip(sx, sy, dx, dy):
        p = Ts @ [x, y, 1.0]
        q = Td @ [u, v, 1.0]
        rows.append([*p, 0.0, 0.0, 0.0, *(-q[0] * p)])
        rows.append([0.0, 0.0, 0.0, *p, *(-q[1] * p)])
    Hn = np.linalg.svd(np.array(rows))[2][-1].reshape(3, 3)
    H = np.linalg.inv(Td) @ Hn @ Ts
    H = H / H[2, 2]
    if refine:
        H = np.append(_reference_refine(H.ravel()[:8], sx, sy, dx, dy), 1.0).reshape(3, 3)
    return H


def _noisy_grid(seed: int) -> tuple[Array, Array, Array, Array]:
    """81 points of a 9 x 9 grid of ±12°, a sensor-like homography, noise on both sides."""
    rng = np.random.default_rng(seed)
    H = np.array(
        [
            [1 + rng.normal(0, 0.01), rng.normal(0, 0.01), rng.normal(0, 0.1)],
            [rng.normal(0, 0.01), 1 + rng.normal(0, 0.01), rng.normal(0, 0.1)],
            [rng.normal(0, 1e-4), rng.normal(0, 1e-4), 1.0],
        ]
    )
    g = np.linspace(-12.0, 12.0, 9)
    x, y = (a.ravel() + rng.normal(0, 0.01, 81) for a in np.meshgrid(g, g))
    u, v = apply_projective(H, x, y)
    return x, y, u + rng.normal(0, 0.003, 81), v + rng.normal(0, 0.003, 81)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("refine", [True, False])
def test_fit_equals_the_reference_implementation(seed: int, refine: bool) -> None:
    x, y, u, v = _noisy_grid(1000 + seed)
    assert np.allclose(
        fit_projective(x, y, u, v, refine=refine),
        _reference_fit(x, y, u, v, refine),
        rtol=1e-10,
        atol=0,
    )


def test_transfer_residuals_equal_the_reference() -> None:
    x, y, u, v = _noisy_grid(2000)
    h = fit_projective(x, y, u, v).ravel()[:8]
    r, J = transfer_residuals(h, x, y, u, v)
    r_ref, J_ref = _reference_transfer(h, x, y, u, v)
    assert np.allclose(r, r_ref, rtol=0, atol=1e-12)  # differences of ~12° angles: rounding ~1e-14
    assert np.allclose(J, J_ref, rtol=1e-13, atol=0)
