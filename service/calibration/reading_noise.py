"""The standard uncertainty of ONE reading of the measurement sensor, and the ways it is had.

GUM 4.2: the standard uncertainty of a single observation is the experimental standard deviation of
the observations, not of their means. A stage record is fitted to point means (several readings
each), so the spread of its fit residuals is the noise of a mean; a live reading is one reading. The
readings at one point share its stand (the stage's positioning error, the point's true tilt), so
their scatter about the point's mean is the sensor's own reading noise: pooled over the points, with
Σ(n_i − 1) degrees of freedom. The fit's own estimate (the meas-vs-ref residual less the reference's
noise) is in `service.calibration.methods.stage.base.meas_reading_noise`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass


@dataclass(frozen=True)
class ReadingNoise:
    """The standard uncertainty of one measurement-sensor reading, in table-tilt degrees, and how it
    was had.

    The meas-vs-ref fit's residual holds both sensors' noise (and any misfit of the model); only the
    measurement sensor's belongs to a corrected reading, since the validation truth, the table tilt,
    is what the reference reads *without* its noise.
    """

    sigma_deg: float
    dof: float
    source: str  # where the estimate comes from, said wherever it is used
    ref_sigma_deg: float | None = None


def pooled_reading_noise(
    points: Iterable[tuple[int, float | None, float | None]],
) -> ReadingNoise | None:
    """Pooled within-point standard deviation of (n_readings, sd_x, sd_y) per point (sd with n − 1),
    the larger axis's (the correction applies one figure to both); None without a point of two or
    more readings."""
    sum_x = sum_y = 0.0
    dof = used = 0
    for n, sd_x, sd_y in points:
        if (
            n < 2
            or sd_x is None
            or sd_y is None
            or not (math.isfinite(sd_x) and math.isfinite(sd_y))
        ):
            continue
        sum_x += (n - 1) * sd_x**2
        sum_y += (n - 1) * sd_y**2
        dof += n - 1
        used += 1
    if dof == 0:
        return None
    return ReadingNoise(
        math.sqrt(max(sum_x, sum_y) / dof),
        float(dof),
        f"pooled within-point standard deviation of the measurement sensor's readings at {used}"
        f" calibration points ({dof} degrees of freedom)",
    )
