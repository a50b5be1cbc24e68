"""A stage record's residual map: per point, the measurement sensor against the reference sensor
before correction (raw) and after it (through the record's model, the computation of `correct`)."""

from __future__ import annotations

from typing import Any, Literal, TypedDict

import numpy as np
from numpy.typing import NDArray

from service.calibration.model import CalibrationModel


class ResidualMapPoint(TypedDict):
    """One point of the map: its index, whether it was fitted on or validates, the stage's and the
    reference's angles, and meas − ref before and after correction (degrees)."""

    point: int
    role: Literal["fit", "validation"]
    stage_x_deg: float
    stage_y_deg: float
    ref_x_deg: float
    ref_y_deg: float
    before_x_deg: float
    after_x_deg: float
    before_y_deg: float
    after_y_deg: float


class ResidualMap(TypedDict):
    """A stage record's residual map: the points fitted on, the RMS vector length before and after
    correction (degrees; None without points) and the points."""

    n_fit: int
    rms_before_deg: float | None
    rms_after_deg: float | None
    points: list[ResidualMapPoint]


def stage_residual_map(
    method: Any, model: CalibrationModel, cols: dict[str, NDArray[np.float64]], n_fit: int
) -> ResidualMap:
    """Points (`role` fit for the first `n_fit` point indices, else validation) with their residuals
    in degrees, and the RMS of the residual vector lengths before and after correction."""
    out = method.correct(model, cols)
    ref = {axis: cols[f"ref_{axis}_deg"] for axis in ("x", "y")}
    before = {axis: cols[f"meas_{axis}_deg"] - ref[axis] for axis in ("x", "y")}
    after = {axis: out[f"tilt_{axis}_deg"] - ref[axis] for axis in ("x", "y")}
    points: list[ResidualMapPoint] = []
    for i in range(cols["point"].size):
        point: ResidualMapPoint = {
            "point": int(cols["point"][i]),
            "role": "fit" if cols["point"][i] < n_fit else "validation",
            "stage_x_deg": float(cols["stage_x_deg"][i]),
            "stage_y_deg": float(cols["stage_y_deg"][i]),
            "ref_x_deg": float(ref["x"][i]),
            "ref_y_deg": float(ref["y"][i]),
            "before_x_deg": float(before["x"][i]),
            "after_x_deg": float(after["x"][i]),
            "before_y_deg": float(before["y"][i]),
            "after_y_deg": float(after["y"][i]),
        }
        points.append(point)
    return {
        "n_fit": min(n_fit, len(points)),
        "rms_before_deg": _rms(np.hypot(before["x"], before["y"])),
        "rms_after_deg": _rms(np.hypot(after["x"], after["y"])),
        "points": points,
    }


def _rms(lengths: NDArray[np.float64]) -> float | None:
    return float(np.sqrt(np.mean(lengths**2))) if lengths.size else None
