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
from scipy.linalg import lapack

from service.errors import DegenerateDataError

# The refinement stops when a step changes no parameter by more than REFINE_STEP_TOL of its size
# (convergence near the optimum is about quadratic: what remains is far smaller again), or the sum
# of squares by less than REFINE_COST_TOL (relatively; its rounding noise is ~1e-13): from the
# DLT's start that is two Gauss-Newton steps.
REFINE_STEP_TOL = 1e-7
REFINE_COST_TOL = 1e-12
REFINE_MAX_ITERATIONS = 50
SQRT2 = float(np.sqrt(2.0))


def check_general_position(
    x: NDArray[np.float64], y: NDArray[np.float64], what: str = "points"
) -> None:
    """At least 4 distinct points, not all on one line: otherwise a homography is undetermined."""
    pts = np.unique(np.round(np.column_stack([x, y]), 9), axis=0)
    if len(pts) < 4:
        raise DegenerateDataError(
            f"{what}: a homography needs at least 4 distinct points, got {len(pts)}"
        )
    centred = pts - pts.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-12):
        raise DegenerateDataError(
            f"{what}: all {len(pts)} points lie on one line; a homography needs points "
            "off that line (e.g. both stage axes moved)"
        )


def _clearly_general(X: NDArray[np.float64], M: list[list[float]]) -> bool:
    """Whether both point sets (rows 0, 1 and 3, 4 of X; M their scatter matrix) clearly pass
    `check_general_position`: 4 sorted values of x or of y, evenly picked, clearly apart (so at
    least 4 distinct points), and a 2 x 2 scatter whose determinant is far from zero. Data that are
    not clearly fine get the full check and its message."""
    n = X.shape[1]
    if n < 4:
        return False
    k = (n - 1) // 3
    picks = np.sort(X, axis=1)[:, : 3 * k + 1 : k].tolist()
    gap = 1e-6 * (1.0 + max(max(row[3], -row[0]) for row in picks))  # far above the check's 1e-9
    for i, j in ((0, 1), (3, 4)):
        picks_i, picks_j = picks[i], picks[j]
        if not (
            min(picks_i[1] - picks_i[0], picks_i[2] - picks_i[1], picks_i[3] - picks_i[2]) > gap
            or min(picks_j[1] - picks_j[0], picks_j[2] - picks_j[1], picks_j[3] - picks_j[2]) > gap
        ):
            return False
        s_ii, s_ij, s_jj = M[i][i], M[i][j], M[j][j]
        if not s_ii * s_jj - s_ij * s_ij > 1e-6 * (s_ii + s_jj) ** 2:
            return False
    return True


def _points(
    sx: NDArray[np.float64],
    sy: NDArray[np.float64],
    dx: NDArray[np.float64],
    dy: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Rows src x, src y, 1, dst x, dst y: the layout the transfer error and its Jacobian read."""
    layout = np.empty((5, sx.size))
    layout[0], layout[1], layout[2], layout[3], layout[4] = sx, sy, 1.0, dx, dy
    return layout


class _Transfer:
    """The transfer error of H = (h8, 1) on fixed points, and its Jacobian, in buffers allocated
    once (the refinement evaluates both a few times on the same points). Both come with the opposite
    sign, dst - H·src and -J, which saves a negation in each and leaves JᵀJ and Jᵀr as they are."""

    def __init__(self, X: NDArray[np.float64]) -> None:
        self.S = X[0:3]  # src x, y, 1
        self.D = X[3:5]  # dst x, y
        self.H = np.empty((3, 3))
        self.H[2, 2] = 1.0
        self.h = self.H.reshape(9)
        # -Jᵀ: parameter x (x residuals, y residuals) x point; the zero blocks stay zero
        self.Kt = np.zeros((8, 2, X.shape[1]))

    def negative_residuals(
        self, h8: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """(dst - H·src, 2 x n with rows x and y; -(H·src), 2 x n; -1/w per point)."""
        self.h[:8] = h8
        num = self.H @ self.S
        neg_w_inv: NDArray[np.float64] = np.divide(-1.0, num[2])
        neg_p: NDArray[np.float64] = num[:2] * neg_w_inv
        return neg_p + self.D, neg_p, neg_w_inv

    def negative_jacobian_t(
        self, neg_p: NDArray[np.float64], neg_w_inv: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """-Jᵀ (8 x 2n; columns the x residuals, then the y residuals) from what
        `negative_residuals` gave."""
        Kt = self.Kt
        # ∂/∂(h11 h12 h13) of the x residual: (sx, sy, 1)/w
        np.multiply(self.S, neg_w_inv, out=Kt[0:3, 0])
        Kt[3:6, 1] = Kt[0:3, 0]  # the y residual's likewise
        # ∂/∂(h31, h32): -(mapped point) · (sx, sy)/w
        np.multiply(Kt[0:2, 0, None], neg_p, out=Kt[6:8])
        return Kt.reshape(8, -1)


def transfer_residuals(
    h8: NDArray[np.float64],
    sx: NDArray[np.float64],
    sy: NDArray[np.float64],
    dx: NDArray[np.float64],
    dy: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Transfer error [H·src - dst in x; in y] (2n) of H = (h8, 1) and, analytically, its Jacobian
    (2n x 8)."""
    t = _Transfer(_points(*(np.asarray(coord, dtype=float) for coord in (sx, sy, dx, dy))))
    neg_r, neg_p, neg_w_inv = t.negative_residuals(np.asarray(h8, dtype=float))
    return -neg_r.ravel(), -t.negative_jacobian_t(neg_p, neg_w_inv).T


def _refine(h: NDArray[np.float64], X: NDArray[np.float64]) -> NDArray[np.float64]:
    """Least squares of the transfer error from the DLT's start: Levenberg-Marquardt with the
    analytic Jacobian, columns scaled to unit norm (the perspective terms are orders of magnitude
    smaller). The normal equations come straight from the (scaled) Jᵀ, 8 x 2n: JᵀJ and Jᵀr are two
    products."""
    estimate = h  # the DLT's, then each accepted step's
    t = _Transfer(X)
    neg_R, neg_p, neg_w_inv = t.negative_residuals(estimate)
    residual = neg_R.ravel()  # the residuals' sign does not matter below: only with the Jacobian's
    cost = float(np.vdot(residual, residual))
    Kt = t.negative_jacobian_t(neg_p, neg_w_inv)
    normal = Kt @ Kt.T
    norms = np.sqrt(normal.diagonal())  # the columns' scales hardly move: taken once
    norms[norms == 0] = 1.0
    inv_norms = 1.0 / norms
    normal *= np.multiply.outer(inv_norms, inv_norms)
    gradient = (Kt @ residual) * inv_norms
    neg_inv_norms = -inv_norms
    damping = 0.0
    for _ in range(REFINE_MAX_ITERATIONS):
        if damping:
            damped = normal.copy()
            damped.flat[::9] *= 1.0 + damping
        else:
            damped = normal
        _, _, step, info = lapack.dgesv(damped, gradient)  # LU with pivoting, as np.linalg.solve
        if info:  # singular: no step (damp harder)
            step = np.full(8, np.nan)
        step *= neg_inv_norms
        trial: NDArray[np.float64] = estimate + step
        neg_R, neg_p, neg_w_inv = t.negative_residuals(trial)
        r_new = neg_R.ravel()
        cost_new = float(np.vdot(r_new, r_new))
        # worse (or not finite): damp harder, same Jacobian
        if not cost_new <= cost * (1.0 + REFINE_COST_TOL):
            damping = max(10.0 * damping, 1e-6)
            if damping > 1e12:
                break
            continue
        if cost - cost_new <= REFINE_COST_TOL * cost or all(
            abs(step_i) <= REFINE_STEP_TOL * (abs(value_i) + REFINE_STEP_TOL)
            for step_i, value_i in zip(step.tolist(), estimate.tolist())
        ):
            return trial
        estimate, residual, cost = trial, r_new, cost_new
        Kt = t.negative_jacobian_t(neg_p, neg_w_inv)
        Kt *= inv_norms[:, None]
        normal = Kt @ Kt.T
        gradient = Kt @ residual
        damping *= 0.1
    return estimate


def fit_projective(
    src_x: ArrayLike,
    src_y: ArrayLike,
    dst_x: ArrayLike,
    dst_y: ArrayLike,
    refine: bool = True,
    what: str = "points",
) -> NDArray[np.float64]:
    """H with dst ~ H · src (homogeneous), h33 = 1."""
    sx, sy, dx, dy = (np.asarray(coord, dtype=float) for coord in (src_x, src_y, dst_x, dst_y))
    n = sx.size
    layout = _points(sx, sy, dx, dy)
    centre = layout.sum(axis=1) / n
    centred = layout - centre[:, None]  # the row of ones becomes zeros
    # both point sets at once; only data that are not clearly fine get the full check and its
    # message
    if not _clearly_general(layout, (centred @ centred.T).tolist()):
        check_general_position(sx, sy, what)
        check_general_position(dx, dy, what)
    # Hartley's normalisation of each set: centroid at 0, mean distance from it √2
    ss, ds = (
        SQRT2 * n / spread if spread > 0 else 1.0
        for spread in np.hypot(centred[0::3], centred[1::3]).sum(axis=1).tolist()
    )
    # Aᵀ of the DLT system A h = 0: per point an x row (P, 0, -u P) and a y row (0, P, -v P), with P
    # and (u, v) the normalised source and target points
    At = np.zeros((9, 2, n))
    np.multiply(centred[0:2], ss, out=At[0:2, 0])
    At[2, 0] = 1.0
    At[3:6, 1] = At[0:3, 0]
    np.multiply(At[0:3, 0, None], centred[3:5] * -ds, out=At[6:9])
    At2 = At.reshape(9, 2 * n)
    hn = _dlt_null_vector(At2, n, what)
    h8 = _denormalised_h8(hn, ss, ds, centre.tolist(), what)
    estimate = np.array(h8)
    if refine and n > 4:
        estimate = _refine(estimate, layout)
    return np.append(estimate, 1.0).reshape(3, 3)


def _dlt_null_vector(At2: NDArray[np.float64], n: int, what: str) -> list[float]:
    """The normalised DLT's solution Hn (9 entries): the null vector of A, whose Aᵀ is `At2`."""
    # The null vector of A from the 9 x 9 AᵀA (eigenvalues = squared singular values) when the 8th
    # is clearly above rounding; otherwise from the SVD of A itself, which also tells a
    # rank-deficient system.
    lam, vec, info = lapack.dsyevd(At2 @ At2.T, lower=1)  # as np.linalg.eigh
    if info == 0 and lam[1] > 1e-8 * lam[-1]:
        hn: list[float] = vec[:, 0].tolist()
        return hn
    # U is not needed (2n x 2n: O(n²) memory); all 9 rows of V are, also with only 4 points
    _, sing, vt = np.linalg.svd(At2.T, full_matrices=2 * n < 9)
    # the 8 free entries of H need rank 8 (sing[7] is the 8th singular value, with 4 points the
    # last)
    if sing[7] <= 1e-12 * sing[0]:
        raise DegenerateDataError(
            f"{what}: the points do not determine a homography (rank-deficient system)"
        )
    hn = vt[-1].tolist()
    return hn


def _denormalised_h8(
    hn: list[float], ss: float, ds: float, centre: list[float], what: str
) -> list[float]:
    """Hn taken back from Hartley's normalisation to the points' units, h33 = 1: H's 8 entries."""
    scx, scy, _, dcx, dcy = centre
    # H = Td⁻¹ Hn Ts, with Ts = [[s, 0, -s cx], [0, s, -s cy], [0, 0, 1]] (Td likewise), entry by
    # entry
    rows = [hn[0:3], hn[3:6], hn[6:9]]
    rows = [
        [ss * coef_x, ss * coef_y, coef_1 - ss * (scx * coef_x + scy * coef_y)]
        for coef_x, coef_y, coef_1 in rows
    ]
    last = rows[2]
    if abs(last[2]) < 1e-12:
        raise DegenerateDataError(f"{what}: the fitted homography maps the origin to infinity")
    k = 1.0 / last[2]
    return [
        (entry / ds + cx * last_entry) * k
        for row, cx in ((rows[0], dcx), (rows[1], dcy))
        for entry, last_entry in zip(row, last)
    ] + [last[0] * k, last[1] * k]


def apply_projective(
    H: NDArray[np.float64], x: ArrayLike, y: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    xa = np.asarray(x, dtype=float)
    ya = np.asarray(y, dtype=float)
    denom = H[2, 0] * xa + H[2, 1] * ya + H[2, 2]
    return (H[0, 0] * xa + H[0, 1] * ya + H[0, 2]) / denom, (
        H[1, 0] * xa + H[1, 1] * ya + H[1, 2]
    ) / denom
