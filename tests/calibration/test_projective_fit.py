"""The homography fit: normalised DLT refined to the least-squares optimum of the transfer error,
with an analytic Jacobian that the covariance also uses; degenerate point sets are refused by
name."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from service.calibration.differences import central_jacobian
from service.calibration.projective import apply_projective, fit_projective, transfer_residuals
from service.errors import DegenerateDataError


def _grid(rng: np.random.Generator, n: int = 9) -> tuple[np.ndarray, np.ndarray]:
    g = np.linspace(-12.0, 12.0, n)
    x, y = np.meshgrid(g, g)
    return x.ravel() + rng.normal(0, 0.01, x.size), y.ravel() + rng.normal(0, 0.01, x.size)


def _bench_like_h(rng: np.random.Generator) -> np.ndarray:
    """A homography like a sensor's: near identity, small cross terms, offsets and perspective."""
    return np.array(
        [
            [1 + rng.normal(0, 0.01), rng.normal(0, 0.01), rng.normal(0, 0.1)],
            [rng.normal(0, 0.01), 1 + rng.normal(0, 0.01), rng.normal(0, 0.1)],
            [rng.normal(0, 1e-4), rng.normal(0, 1e-4), 1.0],
        ]
    )


@pytest.mark.parametrize("seed", range(5))
def test_noise_free_points_give_back_the_homography(seed: int) -> None:
    rng = np.random.default_rng(seed)
    H = _bench_like_h(rng)
    x, y = _grid(rng)
    u, v = apply_projective(H, x, y)
    assert np.allclose(fit_projective(x, y, u, v), H, rtol=0, atol=1e-9)


@pytest.mark.parametrize("seed", range(5))
def test_refined_fit_is_the_least_squares_optimum(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    H = _bench_like_h(rng)
    x, y = _grid(rng)
    u, v = apply_projective(H, x, y)
    u, v = u + rng.normal(0, 0.003, u.size), v + rng.normal(0, 0.003, v.size)
    h = fit_projective(x, y, u, v).ravel()[:8]
    r, J = transfer_residuals(h, x, y, u, v)
    # a general solver started from the fit finds nothing lower
    other = least_squares(
        lambda p: transfer_residuals(p, x, y, u, v)[0], h, method="lm", xtol=1e-15, ftol=1e-15
    )
    assert r @ r <= other.cost * 2 * (1 + 1e-10)
    # and the gradient, per unit column of the Jacobian, is zero to rounding
    assert np.abs(J.T @ r / np.linalg.norm(J, axis=0)).max() < 1e-9 * np.sqrt(r @ r)


def test_analytic_jacobian_equals_central_differences() -> None:
    rng = np.random.default_rng(7)
    H = _bench_like_h(rng)
    x, y = _grid(rng)
    u, v = apply_projective(H, x, y)
    h = H.ravel()[:8]
    _, J = transfer_residuals(h, x, y, u, v)
    numeric = central_jacobian(
        lambda p: transfer_residuals(p, x, y, u, v)[0],
        h,
        np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1e-2, 1e-2]),
    )
    assert np.allclose(J, numeric, rtol=1e-7, atol=1e-6)  # central differences: truncation ~1e-7


@pytest.mark.parametrize("side", ["source", "target"])
def test_too_few_distinct_points_are_refused(side: str) -> None:
    x = np.array([0.0, 1.0, 0.0, 0.0, 1.0, 0.0])
    y = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 1.0])
    good_x, good_y = (
        np.array([0.0, 1.0, 0.0, 1.0, 2.0, 3.0]),
        np.array([0.0, 0.0, 1.0, 1.0, 3.0, 2.0]),
    )
    args = (x, y, good_x, good_y) if side == "source" else (good_x, good_y, x, y)
    with pytest.raises(DegenerateDataError, match="at least 4 distinct points, got 3"):
        fit_projective(*args, what="H2")


@pytest.mark.parametrize("side", ["source", "target"])
def test_points_on_one_line_are_refused(side: str) -> None:
    t = np.linspace(-5, 5, 9)
    line_x, line_y = t, 0.5 * t + 1
    rng = np.random.default_rng(3)
    good_x, good_y = _grid(rng, 3)
    args = (
        (line_x, line_y, good_x, good_y) if side == "source" else (good_x, good_y, line_x, line_y)
    )
    with pytest.raises(DegenerateDataError, match="lie on one line"):
        fit_projective(*args, what="H1")
