"""The item's indication error as found, with its uncertainty, at every point a stage job measured.

Pure. At each point both sensors were read `n` times after the table settled; the point's values
are the means. The reference value's standard uncertainty combines the reference standards'
(u = U/k of their certificates, the reference sensor's angle scale comes from them), the reference
sensor's resolution (r/√12) and the noise of its mean (s/√n, n − 1 degrees of freedom); the
item's indication has its own resolution and the noise of its mean; the indication error
(indication − reference) combines both. Degrees of freedom by Welch-Satterthwaite (the components
are independent estimates), k from Student's t at 95 %.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.calibration.budget import SQRT12, Component
from service.calibration.uncertainty import COVERAGE, coverage_factor

AXES = ("x", "y")
# one independent part of an uncertainty: (u_i, ν_i) per point
_Part = tuple[NDArray[np.float64], NDArray[np.float64]]


@dataclass(frozen=True)
class MeasuredPoint:
    """One settled point of a stage job: both sensors' means, their standard deviations and
    counts."""

    point: int
    fitted: bool  # used by the fit (a calibration point), else a validation point
    reference_deg: tuple[float, float]
    indication_deg: tuple[float, float]
    reference_std_deg: tuple[float | None, float | None] = (None, None)
    indication_std_deg: tuple[float | None, float | None] = (None, None)
    reference_n: int = 1
    indication_n: int = 1


@dataclass(frozen=True)
class Uncertain:
    """Values with their standard uncertainties, effective degrees of freedom, coverage factors and
    U (per point)."""

    value: NDArray[np.float64]
    u: NDArray[np.float64]
    dof: NDArray[np.float64]
    k: NDArray[np.float64]

    @property
    def expanded_u(self) -> NDArray[np.float64]:
        return self.k * self.u


@dataclass(frozen=True)
class AxisAsFound:
    reference: Uncertain
    indication: Uncertain
    error: Uncertain


def _noise(
    std: Sequence[float | None], n: Sequence[int]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The standard uncertainty of each point's mean (s/√n) and its degrees of freedom (n − 1); zero
    where unknown."""
    u_mean = np.array(
        [
            spread / math.sqrt(count) if spread is not None and count > 1 else 0.0
            for spread, count in zip(std, n, strict=True)
        ]
    )
    dof = np.array(
        [
            float(count - 1) if spread is not None and count > 1 else math.inf
            for spread, count in zip(std, n, strict=True)
        ]
    )
    return u_mean, dof


def _combined(
    value: NDArray[np.float64],
    parts: Sequence[tuple[NDArray[np.float64], NDArray[np.float64]]],
    coverage: float,
) -> Uncertain:
    """Root sum of squares of independent parts (u_i, ν_i) per point, Welch-Satterthwaite, k from
    Student's t."""
    var = sum((u_part**2 for u_part, _ in parts), np.zeros_like(value))
    denom = sum(
        (
            np.where(np.isfinite(nu), u_part**4 / np.where(np.isfinite(nu), nu, 1.0), 0.0)
            for u_part, nu in parts
        ),
        np.zeros_like(value),
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        dof = np.where(denom > 0, var**2 / np.where(denom > 0, denom, 1.0), np.inf)
    return Uncertain(
        value, np.sqrt(var), dof, np.asarray(coverage_factor(dof, coverage), dtype=float)
    )


def _resolution_part(n: int, resolution_deg: float | None) -> list[_Part]:
    """A sensor's resolution as a rectangular part (r/√12, exact), none when it is not stated."""
    if not resolution_deg:
        return []
    return [(np.full(n, resolution_deg / SQRT12), np.full(n, math.inf))]


def _reference_parts(
    points: Sequence[MeasuredPoint],
    axis_index: int,
    standards: Sequence[Component],
    resolution_deg: float | None,
) -> list[_Part]:
    """The reference value's parts on one axis: the standards, the sensor's resolution and the noise
    of its mean."""
    n = len(points)
    parts: list[_Part] = [
        (np.full(n, standard.u_deg), np.full(n, standard.dof)) for standard in standards
    ]
    parts += _resolution_part(n, resolution_deg)
    parts.append(
        _noise(
            [point.reference_std_deg[axis_index] for point in points],
            [point.reference_n for point in points],
        )
    )
    return parts


def _indication_parts(
    points: Sequence[MeasuredPoint], axis_index: int, resolution_deg: float | None
) -> list[_Part]:
    """The item's indication's parts on one axis: its resolution and the noise of its mean."""
    parts = _resolution_part(len(points), resolution_deg)
    parts.append(
        _noise(
            [point.indication_std_deg[axis_index] for point in points],
            [point.indication_n for point in points],
        )
    )
    return parts


def as_found(
    points: Sequence[MeasuredPoint],
    standards: Sequence[Component],
    reference_resolution_deg: float | None,
    indication_resolution_deg: float | None,
    coverage: float = COVERAGE,
) -> dict[str, AxisAsFound]:
    """Per axis: the reference values, the item's indications and the indication errors, each with
    its uncertainty."""
    out: dict[str, AxisAsFound] = {}
    for i, axis in enumerate(AXES):
        ref = np.array([point.reference_deg[i] for point in points], dtype=float)
        ind = np.array([point.indication_deg[i] for point in points], dtype=float)
        ref_parts = _reference_parts(points, i, standards, reference_resolution_deg)
        ind_parts = _indication_parts(points, i, indication_resolution_deg)
        out[axis] = AxisAsFound(
            _combined(ref, ref_parts, coverage),
            _combined(ind, ind_parts, coverage),
            _combined(ind - ref, ref_parts + ind_parts, coverage),
        )
    return out


def single_reading_noise(points: Sequence[MeasuredPoint]) -> dict[str, tuple[float, float]] | None:
    """The item's noise of one reading per axis, pooled over the points (s, degrees of freedom);
    None when the points do not state their spread."""
    out: dict[str, tuple[float, float]] = {}
    for i, axis in enumerate(AXES):
        pairs = [
            (point.indication_std_deg[i], point.indication_n)
            for point in points
            if point.indication_std_deg[i] is not None and point.indication_n > 1
        ]
        if not pairs:
            return None
        dof = sum(n - 1 for _, n in pairs)
        variance = (
            sum((n - 1) * float(spread) ** 2 for spread, n in pairs if spread is not None) / dof
        )
        out[axis] = (math.sqrt(variance), float(dof))
    return out
