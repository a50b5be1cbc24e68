"""Where the noise level comes from: repeated points, the instrument's specification, or the final
residual."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

MIN_REPEAT_DOF = 5  # fewer repeat degrees of freedom than this do not make a usable noise estimate


@dataclass
class NoiseLevel:
    # per axis, in the data's unit; None until the final residual gives it
    sigma: NDArray[np.float64] | None
    source: str  # "repeated points", "instrument specification", "final residual"
    df: float  # degrees of freedom of the estimate (inf for a specification)
    detail: str

    @property
    def known(self) -> bool:
        return self.sigma is not None


def from_repeats(
    observed: NDArray[np.float64], groups: NDArray[np.float64] | None
) -> NoiseLevel | None:
    """Pooled standard deviation of rows that share a group key (grid point and approach
    direction)."""
    if groups is None:
        return None
    keys, inv = np.unique(groups, axis=0, return_inverse=True)
    inv = inv.ravel()
    counts = np.bincount(inv)
    dof = int(np.sum(counts[counts > 1] - 1))
    if dof < MIN_REPEAT_DOF:
        return None
    per_axis = []
    for axis in range(observed.shape[1]):
        col = observed[:, axis]
        means = np.bincount(inv, weights=col) / counts
        ss = float(np.sum((col - means[inv]) ** 2))
        per_axis.append(np.sqrt(ss / dof))
    sig = np.array(per_axis)
    if np.any(sig <= 0):
        return None
    n_rep = int(np.sum(counts > 1))
    return NoiseLevel(
        sig,
        "repeated points",
        float(dof),
        f"pooled scatter of {n_rep} repeated points ({dof} degrees of freedom); rows count as "
        "repeats when they share the grid point and the approach direction, so backlash is not "
        "taken for noise (drift between the repeats is, which makes the level conservative)",
    )


def from_specification(sigma: ArrayLike) -> NoiseLevel:
    sigma_per_axis = np.atleast_1d(np.asarray(sigma, dtype=float))
    return NoiseLevel(
        sigma_per_axis,
        "instrument specification",
        float("inf"),
        "1-sigma noise of one reading as given with the data (instrument specification)",
    )


def from_residual(resid: NDArray[np.float64], k: int) -> NoiseLevel:
    """Per-axis residual standard deviation of the final model, corrected for the fitted
    parameters."""
    n, n_axes = resid.shape
    dof_total = resid.size - k
    frac = max(dof_total, 1) / resid.size
    sig = np.sqrt(np.sum(resid**2, axis=0) / (n * frac))
    return NoiseLevel(
        sig,
        "final residual",
        float(max(dof_total, 1)),
        "no repeated points and no instrument specification: the noise level is the residual "
        "standard deviation of the final model, and every test used the residual of the "
        "extended model as its denominator (F-tests)",
    )
