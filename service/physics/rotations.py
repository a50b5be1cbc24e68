"""Rotations as the bench sees them: right-handed, angles in radians, vectorised over points."""

from __future__ import annotations

import numpy as np


def rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def plane_tilt(tilt_x: float, tilt_y: float) -> np.ndarray:
    """Orientation of a plane tilted so that it adds about (tilt_x, tilt_y) to (x, y) readings.

    Same composition as the stacked stage of docs/models.md §2: R = Rx(-tilt_y) · Ry(tilt_x).
    """
    return rx(-tilt_y) @ ry(tilt_x)


def rotate_about(v: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues' rotation of vectors v (..., 3) about a fixed unit axis by per-point angles (...)."""
    c = np.cos(angle)[..., None]
    s = np.sin(angle)[..., None]
    axis = np.asarray(axis, dtype=float)
    cross = np.cross(axis, v)
    dot = (v @ axis)[..., None]
    return v * c + cross * s + axis * dot * (1.0 - c)


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)
