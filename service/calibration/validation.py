"""Where a calibration's validation points are: drawn reproducibly from the request's size (a
repeated request measures the same points), so a job, a plan made without a bench and a test all
find them alike. Pure."""

from __future__ import annotations

import numpy as np

from service.calibration.adaptive_design import short_tour


def validation_rng(n_points: int, n_validation: int) -> np.random.Generator:
    """The draw of `n_validation` validation points of a request of `n_points` points."""
    return np.random.default_rng(n_points * 7919 + n_validation)


def stage_validation_points(
    points: list[tuple[float, float]], n_points: int
) -> list[tuple[float, float]]:
    """`n_points` validation points (table tilts, deg) drawn uniformly over the range of the
    stage-grid `points`, in the order of shortest travel from the last of them (a random order
    crossed the range between each two)."""
    xs, ys = np.array(points, dtype=float).T
    rng = validation_rng(len(points), n_points)
    drawn = [
        (float(round(x, 4)), float(round(y, 4)))
        for x, y in zip(
            rng.uniform(xs.min(), xs.max(), n_points),
            rng.uniform(ys.min(), ys.max(), n_points),
        )
    ]
    return short_tour(points[-1], drawn)
