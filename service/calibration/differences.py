"""The one rule for finite-difference derivatives of the calibration code (Jacobians,
sensitivities).

step h = REL_STEP · max(|value|, typical): relative to the value, so parameters in any unit
(counts per arcsec, rad, deg) are stepped alike, and never below REL_STEP times the magnitude
the caller states the quantity typically has, so a value near zero is stepped by something
its function resolves; REL_STEP itself where both are zero. Central differences throughout.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

REL_STEP = 1e-6


def fd_step(value: ArrayLike, typical: ArrayLike = 0.0) -> NDArray[np.float64]:
    """Finite-difference step for `value` (array or scalar) whose typical magnitude is `typical`."""
    step = REL_STEP * np.maximum(
        np.abs(np.asarray(value, dtype=float)), np.asarray(typical, dtype=float)
    )
    return np.where(step > 0, step, REL_STEP)


def central_jacobian(
    fun: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    x: NDArray[np.float64],
    typical: ArrayLike,
) -> NDArray[np.float64]:
    """d fun / d x by central differences, the parameter axis last: (..., n) for fun(x) of shape
    (...)."""
    x = np.asarray(x, dtype=float)
    steps = np.broadcast_to(fd_step(x, typical), x.shape)
    cols = []
    for i in range(x.size):
        offset = np.zeros_like(x)
        offset[i] = steps[i]
        cols.append((np.asarray(fun(x + offset)) - np.asarray(fun(x - offset))) / (2 * steps[i]))
    return np.stack(cols, axis=-1)
