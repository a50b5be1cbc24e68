"""Planar projective maps (homographies) between pairs of angles, by normalised DLT.

Seed 000 treats the grid of stage angles and the grid of sensor angles as two views of one
plane (its eqs. 11-13, h33 = 1), estimated from at least four points in general position.
Hartley's normalisation keeps the linear system well conditioned; an optional refinement
minimises the transfer error in the target space.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from service.errors import DegenerateDataError


def _normaliser(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    cx, cy = x.mean(), y.mean()
    d = np.sqrt((x - cx) ** 2 + (y - cy) ** 2).mean()
    s = np.sqrt(2.0) / d if d > 0 else 1.0
    return np.array([[s, 0.0, -s * cx], [0.0, s, -s * cy], [0.0, 0.0, 1.0]])


def check_general_position(x: np.ndarray, y: np.ndarray, what: str = "points") -> None:
    """At least 4 distinct points, not all on one line: otherwise a homography is undetermined."""
    pts = np.unique(np.round(np.column_stack([x, y]), 9), axis=0)
    if len(pts) < 4:
        raise DegenerateDataError(f"{what}: a homography needs at least 4 distinct points, got {len(pts)}")
    c = pts - pts.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-12):
        raise DegenerateDataError(f"{what}: all {len(pts)} points lie on one line; a homography needs points "
                                  "off that line (e.g. both stage axes moved)")


def fit_projective(src_x, src_y, dst_x, dst_y, refine: bool = True, what: str = "points") -> np.ndarray:
    """H with dst ~ H · src (homogeneous), h33 = 1."""
    sx, sy, dx, dy = (np.asarray(v, dtype=float) for v in (src_x, src_y, dst_x, dst_y))
    check_general_position(sx, sy, what)
    check_general_position(dx, dy, what)
    Ts, Td = _normaliser(sx, sy), _normaliser(dx, dy)
    ps = Ts @ np.vstack([sx, sy, np.ones_like(sx)])
    pd = Td @ np.vstack([dx, dy, np.ones_like(dx)])
    n = sx.size
    A = np.zeros((2 * n, 9))
    X, Y = ps[0], ps[1]
    u, v = pd[0], pd[1]
    A[0::2, 0:3] = np.column_stack([X, Y, np.ones(n)])
    A[0::2, 6:9] = -u[:, None] * np.column_stack([X, Y, np.ones(n)])
    A[1::2, 3:6] = np.column_stack([X, Y, np.ones(n)])
    A[1::2, 6:9] = -v[:, None] * np.column_stack([X, Y, np.ones(n)])
    # U is not needed (2n x 2n: O(n²) memory); all 9 rows of V are, also with only 4 points
    _, s, vt = np.linalg.svd(A, full_matrices=A.shape[0] < A.shape[1])
    # the 8 free entries of H need rank 8 (s[7] is the 8th singular value, with 4 points the last)
    if s[7] <= 1e-12 * s[0]:
        raise DegenerateDataError(f"{what}: the points do not determine a homography (rank-deficient system)")
    Hn = vt[-1].reshape(3, 3)
    H = np.linalg.inv(Td) @ Hn @ Ts
    if abs(H[2, 2]) < 1e-12:
        raise DegenerateDataError(f"{what}: the fitted homography maps the origin to infinity")
    H = H / H[2, 2]
    if refine and n > 4:
        def resid(h):
            Hh = np.append(h, 1.0).reshape(3, 3)
            px, py = apply_projective(Hh, sx, sy)
            return np.concatenate([px - dx, py - dy])

        sol = least_squares(resid, H.ravel()[:8], method="lm", xtol=1e-14, ftol=1e-14)
        H = np.append(sol.x, 1.0).reshape(3, 3)
    return H


def apply_projective(H: np.ndarray, x, y) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    return (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w, (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w
