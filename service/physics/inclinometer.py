"""What an inclinometer axis reads (docs/models.md §1): the angle between the axis and the
horizontal."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def sensor_axes(yaw: float, non_orthogonality: float, flip: str = "none") -> NDArray[np.float64]:
    """Unit x and y sensing axes (rows) in the frame of the sensor's seat.

    The y axis is turned by `non_orthogonality` (radians) away from 90 deg to x; `flip`
    ("x" or "y") is a sensor mounted upside down, turned 180 deg about that axis, which
    mirrors the other axis.
    """
    cy, sy = np.cos(yaw), np.sin(yaw)
    x = np.array([1.0, 0.0, 0.0])
    y = np.array([-np.sin(non_orthogonality), np.cos(non_orthogonality), 0.0])
    if flip == "x":
        y = y * np.array([1.0, -1.0, -1.0])
    elif flip == "y":
        x = x * np.array([-1.0, 1.0, -1.0])
        y = y * np.array([-1.0, 1.0, -1.0])
    elif flip != "none":
        raise ValueError(f"flip must be 'none', 'x' or 'y', not {flip!r}")
    yaw_m = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return np.stack([yaw_m @ x, yaw_m @ y])


def apply_reading_errors(
    true_deg: NDArray[np.float64],
    *,
    zero_deg: float = 0.0,
    scale: float = 0.0,
    quad_per_deg: float = 0.0,
    temp_delta_k: NDArray[np.float64] | float = 0.0,
    zero_per_k: float = 0.0,
    scale_per_k: float = 0.0,
    drift_deg: NDArray[np.float64] | float = 0.0,
    noise_deg: NDArray[np.float64] | float = 0.0,
    resolution_deg: float = 0.0,
) -> NDArray[np.float64]:
    """The error terms a real sensor adds to the geometric angle (docs/models.md §1, named in
    §5)."""
    reading_deg = (
        true_deg * (1.0 + scale + scale_per_k * temp_delta_k)
        + quad_per_deg * true_deg**2
        + zero_deg
        + zero_per_k * temp_delta_k
        + drift_deg
        + noise_deg
    )
    if resolution_deg > 0:
        reading_deg = np.round(reading_deg / resolution_deg) * resolution_deg
    return reading_deg
