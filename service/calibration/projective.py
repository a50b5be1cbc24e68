"""Planar projective maps (homographies) between pairs of angles, by normalised DLT.

Seed 000 treats the grid of stage angles and the grid of sensor angles as two views of one
plane (its eqs. 11-13, h33 = 1), estimated from at least four points in general position.
Hartley's normalisation keeps the linear system well conditioned; an optional refinement
minimises the transfer error in the target space (Levenberg-Marquardt on the analytic Jacobian,
which also gives the fit's covariance).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.errors import DegenerateDataError

# The refinement stops when a step changes no parameter by more than REFINE_STEP_TOL of its size
# (convergence near the optimum is about quadratic: what remains is far smaller again), or the sum
# of squares by less than REFINE_COST_TOL (relatively; its rounding noise is ~1e-13): from the
# DLT's start that is two Gauss-Newton steps.
REFINE_STEP_TOL = 1e-7
REFINE_COST_TOL = 1e-12
REFINE_MAX_ITERATIONS = 50


def _normaliser(x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[float, float, float]:
    """Hartley's normalisation (scale s, centre cx, cy): centroid at 0, mean distance from it √2."""
    n = x.size
    cx, cy = float(x.sum()) / n, float(y.sum()) / n
    d = float(np.sqrt((x - cx) ** 2 + (y - cy) ** 2).sum()) / n
    s = float(np.sqrt(2.0)) / d if d > 0 else 1.0
    return s, cx, cy


def _distinct_and_spread(x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """Per row of x, y (k x n): the number of distinct points (to 1e-9), and whether they are clearly
    spread in two directions (the 2 x 2 scatter's determinant far from zero)."""
    z = np.sort(np.round(x, 9) + 1j * np.round(y, 9), axis=-1)
    distinct = np.count_nonzero(z[:, 1:] != z[:, :-1], axis=-1) + 1
    cx = x - x.sum(axis=-1, keepdims=True) / x.shape[-1]
    cy = y - y.sum(axis=-1, keepdims=True) / y.shape[-1]
    a, b, d = (cx * cx).sum(axis=-1), (cx * cy).sum(axis=-1), (cy * cy).sum(axis=-1)
    return distinct, a * d - b * b > 1e-6 * (a + d) ** 2


def check_general_position(x: NDArray[np.float64], y: NDArray[np.float64], what: str = "points") -> None:
    """At least 4 distinct points, not all on one line: otherwise a homography is undetermined."""
    pts = np.unique(np.round(np.column_stack([x, y]), 9), axis=0)
    if len(pts) < 4:
        raise DegenerateDataError(f"{what}: a homography needs at least 4 distinct points, got {len(pts)}")
    c = pts - pts.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-12):
        raise DegenerateDataError(f"{what}: all {len(pts)} points lie on one line; a homography needs points "
                                  "off that line (e.g. both stage axes moved)")


def _transfer(h8: NDArray[np.float64], sx: NDArray[np.float64], sy: NDArray[np.float64], dx: NDArray[np.float64],
              dy: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(residuals [H·src - dst in x; in y], px, py, 1/w) of H = (h8, 1)."""
    w_inv = 1.0 / (h8[6] * sx + h8[7] * sy + 1.0)
    px = (h8[0] * sx + h8[1] * sy + h8[2]) * w_inv
    py = (h8[3] * sx + h8[4] * sy + h8[5]) * w_inv
    return np.concatenate([px - dx, py - dy]), px, py, w_inv


def _jacobian(sx: NDArray[np.float64], sy: NDArray[np.float64], px: NDArray[np.float64], py: NDArray[np.float64],
              w_inv: NDArray[np.float64]) -> NDArray[np.float64]:
    n = sx.size
    J = np.zeros((2 * n, 8))
    J[:n, 0] = J[n:, 3] = sx * w_inv
    J[:n, 1] = J[n:, 4] = sy * w_inv
    J[:n, 2] = J[n:, 5] = w_inv
    J[:n, 6] = -px * J[:n, 0]
    J[:n, 7] = -px * J[:n, 1]
    J[n:, 6] = -py * J[:n, 0]
    J[n:, 7] = -py * J[:n, 1]
    return J


def transfer_residuals(h8: NDArray[np.float64], sx: NDArray[np.float64], sy: NDArray[np.float64], dx: NDArray[np.float64],
                       dy: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Transfer error [H·src - dst in x; in y] (2n) of H = (h8, 1) and, analytically, its Jacobian (2n x 8)."""
    r, px, py, w_inv = _transfer(h8, sx, sy, dx, dy)
    return r, _jacobian(sx, sy, px, py, w_inv)


def _refine(h: NDArray[np.float64], sx: NDArray[np.float64], sy: NDArray[np.float64], dx: NDArray[np.float64],
            dy: NDArray[np.float64]) -> NDArray[np.float64]:
    """Least squares of the transfer error from the DLT's start: Levenberg-Marquardt with the analytic
    Jacobian, columns scaled to unit norm (the perspective terms are orders of magnitude smaller)."""
    r, J = transfer_residuals(h, sx, sy, dx, dy)
    cost = float(r @ r)
    damping = 0.0
    norms = np.sqrt(np.einsum("ij,ij->j", J, J))  # the columns' scales hardly move: taken once
    norms[norms == 0] = 1.0
    for _ in range(REFINE_MAX_ITERATIONS):
        Js = J / norms
        N = Js.T @ Js
        if damping:
            N = N + damping * np.diag(np.diag(N))
        try:
            step = -np.linalg.solve(N, Js.T @ r) / norms
        except np.linalg.LinAlgError:
            step = np.full(8, np.nan)
        trial: NDArray[np.float64] = h + step
        r_new, px, py, w_inv = _transfer(trial, sx, sy, dx, dy)
        cost_new = float(r_new @ r_new)
        if not cost_new <= cost * (1.0 + REFINE_COST_TOL):  # worse (or not finite): damp harder, same Jacobian
            damping = max(10.0 * damping, 1e-6)
            if damping > 1e12:
                break
            continue
        if (cost - cost_new <= REFINE_COST_TOL * cost
                or np.all(np.abs(step) <= REFINE_STEP_TOL * (np.abs(h) + REFINE_STEP_TOL))):
            return trial
        h, r, cost = trial, r_new, cost_new
        J = _jacobian(sx, sy, px, py, w_inv)
        damping *= 0.1
    return h


def fit_projective(src_x: ArrayLike, src_y: ArrayLike, dst_x: ArrayLike, dst_y: ArrayLike, refine: bool = True,
                   what: str = "points") -> NDArray[np.float64]:
    """H with dst ~ H · src (homogeneous), h33 = 1."""
    sx, sy, dx, dy = (np.asarray(v, dtype=float) for v in (src_x, src_y, dst_x, dst_y))
    # both point sets at once; only data that are not clearly fine get the full check and its message
    distinct, spread = _distinct_and_spread(np.stack([sx, dx]), np.stack([sy, dy]))
    if not (distinct.min() >= 4 and spread.all()):
        check_general_position(sx, sy, what)
        check_general_position(dx, dy, what)
    (ss, scx, scy), (ds, dcx, dcy) = _normaliser(sx, sy), _normaliser(dx, dy)
    n = sx.size
    P = np.empty((n, 3))
    P[:, 0] = ss * (sx - scx)
    P[:, 1] = ss * (sy - scy)
    P[:, 2] = 1.0
    u = ds * (dx - dcx)
    v = ds * (dy - dcy)
    A = np.zeros((2 * n, 9))
    A[0::2, 0:3] = P
    A[0::2, 6:9] = -u[:, None] * P
    A[1::2, 3:6] = P
    A[1::2, 6:9] = -v[:, None] * P
    # The null vector of A from the 9 x 9 AᵀA (eigenvalues = squared singular values) when the 8th is
    # clearly above rounding; otherwise from the SVD of A itself, which also tells a rank-deficient system.
    lam, vec = np.linalg.eigh(A.T @ A)
    if lam[1] > 1e-8 * lam[-1]:
        Hn = vec[:, 0].reshape(3, 3)
    else:
        # U is not needed (2n x 2n: O(n²) memory); all 9 rows of V are, also with only 4 points
        _, s, vt = np.linalg.svd(A, full_matrices=A.shape[0] < A.shape[1])
        # the 8 free entries of H need rank 8 (s[7] is the 8th singular value, with 4 points the last)
        if s[7] <= 1e-12 * s[0]:
            raise DegenerateDataError(f"{what}: the points do not determine a homography (rank-deficient system)")
        Hn = vt[-1].reshape(3, 3)
    Ts = np.array([[ss, 0.0, -ss * scx], [0.0, ss, -ss * scy], [0.0, 0.0, 1.0]])
    Td_inv = np.array([[1.0 / ds, 0.0, dcx], [0.0, 1.0 / ds, dcy], [0.0, 0.0, 1.0]])
    H: NDArray[np.float64] = Td_inv @ Hn @ Ts
    if abs(H[2, 2]) < 1e-12:
        raise DegenerateDataError(f"{what}: the fitted homography maps the origin to infinity")
    H = H / H[2, 2]
    if refine and n > 4:
        H = np.append(_refine(H.ravel()[:8], sx, sy, dx, dy), 1.0).reshape(3, 3)
    return H


def apply_projective(H: NDArray[np.float64], x: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    xa = np.asarray(x, dtype=float)
    ya = np.asarray(y, dtype=float)
    w = H[2, 0] * xa + H[2, 1] * ya + H[2, 2]
    return (H[0, 0] * xa + H[0, 1] * ya + H[0, 2]) / w, (H[1, 0] * xa + H[1, 1] * ya + H[1, 2]) / w
