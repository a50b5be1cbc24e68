"""A stage record's residual map: per point, the measurement sensor against the reference sensor
before correction (raw) and after it (through the record's model, the computation of `correct`)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.calibration.model import CalibrationModel


def stage_residual_map(
    method: Any, model: CalibrationModel, cols: dict[str, NDArray[np.float64]], n_fit: int
) -> dict[str, Any]:
    """Points (`role` fit for the first `n_fit` point indices, else validation) with their residuals
    in degrees, and the RMS of the residual vector lengths before and after correction."""
    out = method.correct(model, cols)
    ref = {axis: cols[f"ref_{axis}_deg"] for axis in ("x", "y")}
    before = {axis: cols[f"meas_{axis}_deg"] - ref[axis] for axis in ("x", "y")}
    after = {axis: out[f"tilt_{axis}_deg"] - ref[axis] for axis in ("x", "y")}
    points = []
    for i in range(cols["point"].size):
        point = {
            "point": int(cols["point"][i]),
            "role": "fit" if cols["point"][i] < n_fit else "validation",
            "stage_x_deg": float(cols["stage_x_deg"][i]),
            "stage_y_deg": float(cols["stage_y_deg"][i]),
            "ref_x_deg": float(ref["x"][i]),
            "ref_y_deg": float(ref["y"][i]),
        }
        for axis in ("x", "y"):
            point[f"before_{axis}_deg"] = float(before[axis][i])
            point[f"after_{axis}_deg"] = float(after[axis][i])
        points.append(point)
    return {
        "n_fit": min(n_fit, len(points)),
        "rms_before_deg": _rms(np.hypot(before["x"], before["y"])),
        "rms_after_deg": _rms(np.hypot(after["x"], after["y"])),
        "points": points,
    }


def _rms(lengths: NDArray[np.float64]) -> float | None:
    return float(np.sqrt(np.mean(lengths**2))) if lengths.size else None
