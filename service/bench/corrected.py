"""The corrected table tilt of a measurement-sensor reading through the active calibration record.

One function, used by `GET /tilt` and the live reading stream alike, so both serve the same numbers.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from service.calibration.uncertainty import COVERAGE
from service.columns import K_OUTPUTS
from service.instruments.base import Reading


def corrected_tilt(active: Any, meas: Reading) -> dict:
    """Table tilt in the reference sensor's frame with its expanded uncertainty (GUM, 95 % coverage) from
    the record's covariance: {"x_deg", "y_deg", "u_x_deg", "u_y_deg", "k", "k_y", "coverage_probability"};
    `k` is the coverage factor of u_x_deg and `k_y` that of u_y_deg, Student's t at the effective
    degrees of freedom (Welch-Satterthwaite), near 2 for a well-determined record; an uncertainty the
    method cannot give is None, and so is its factor. `active` is the job manager's ActiveModel of the bench."""
    out = active.method.correct(active.model, {"meas_x_deg": np.array([meas.x_deg], dtype=float),
                                               "meas_y_deg": np.array([meas.y_deg], dtype=float)})

    def u(k: str) -> float | None:
        return None if k not in out or not np.isfinite(out[k][0]) else float(out[k][0])

    return {"x_deg": float(out["tilt_x_deg"][0]), "y_deg": float(out["tilt_y_deg"][0]),
            "u_x_deg": u("u_tilt_x_deg"), "u_y_deg": u("u_tilt_y_deg"),
            "k": u(K_OUTPUTS[0]) if u("u_tilt_x_deg") is not None else None,
            "k_y": u(K_OUTPUTS[1]) if u("u_tilt_y_deg") is not None else None,
            "coverage_probability": COVERAGE}
