"""Rotations as the bench sees them: right-handed, angles in radians, vectorised over points."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def rx(a: float) -> NDArray[np.float64]:
    cos_a, sin_a = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, cos_a, -sin_a], [0.0, sin_a, cos_a]])


def ry(a: float) -> NDArray[np.float64]:
    cos_a, sin_a = np.cos(a), np.sin(a)
    return np.array([[cos_a, 0.0, sin_a], [0.0, 1.0, 0.0], [-sin_a, 0.0, cos_a]])


def rz(a: float) -> NDArray[np.float64]:
    cos_a, sin_a = np.cos(a), np.sin(a)
    return np.array([[cos_a, -sin_a, 0.0], [sin_a, cos_a, 0.0], [0.0, 0.0, 1.0]])


def plane_tilt(tilt_x: float, tilt_y: float) -> NDArray[np.float64]:
    """Orientation of a plane tilted so that it adds about (tilt_x, tilt_y) to (x, y) readings.

    Same composition as the stacked stage of docs/models.md §2: R = Rx(-tilt_y) · Ry(tilt_x).
    """
    return rx(-tilt_y) @ ry(tilt_x)


def unit(v: ArrayLike) -> NDArray[np.float64]:
    vector = np.asarray(v, dtype=float)
    out: NDArray[np.float64] = vector / np.linalg.norm(vector)
    return out
