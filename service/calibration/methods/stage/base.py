"""What every stage method shares: the columns, the bench it was calibrated for, the levelling
output (refused beyond the bench's travel), the statistics and the GUM correction helper."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import asdict
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.calibration.differences import central_jacobian
from service.calibration.methods.stage.common import (
    MEAS_COLUMNS,
    REF_COLUMNS,
    STAGE_COLUMNS,
    TILT_OUTPUTS,
    columns,
    detect_mirror,
    sign_from_options,
)
from service.calibration.model import CalibrationModel, Parameter
from service.calibration.registry import FitOptions
from service.calibration.uncertainty import coverage_factor, propagate_gum
from service.errors import DegenerateDataError, InputError
from service.io.columns import K_OUTPUTS
from service.physics.stage import ASSUMED_BENCH_SOURCE, StageBench

Columns = Mapping[str, NDArray[np.float64]]
FIT_REQUIRED = STAGE_COLUMNS + REF_COLUMNS
FIT_OPTIONAL = MEAS_COLUMNS + ("dir_x", "dir_y", "temp_c", "t_s", "point")
CROSS_TOL_DEG = 1e-6


def stage_hardware(options: FitOptions) -> tuple[StageBench, str, bool]:
    """The bench the data came from: stated by the caller (options.extra["bench"]) or assumed (seed 000's)."""
    given = options.extra.get("bench")
    if given is None:
        return StageBench(), ASSUMED_BENCH_SOURCE, False
    bench = given if isinstance(given, StageBench) else StageBench(**given)
    return bench, str(options.extra.get("bench_source", "stated by the caller")), True


def bench_state(bench: StageBench, source: str) -> dict[str, Any]:
    """What a stage model keeps of its bench: the hardware (levelling's travel, the kinematic chain) and its source."""
    return {"bench": asdict(bench), "bench_source": source}


def meas_sign(data: Columns, options: FitOptions) -> tuple[NDArray[np.float64], str]:
    mx, my, rx, ry = columns(data, MEAS_COLUMNS + REF_COLUMNS)
    return sign_from_options(options.extra, detect_mirror(mx, my, rx, ry))


def fit_stats(r: NDArray[np.float64], n_par: int) -> dict[str, Any]:
    """Degrees of freedom and residual sigma; no sigma when the points only just determine the parameters."""
    dof = r.size - n_par
    return {"dof": dof, "sigma_deg": float(np.sqrt(r @ r / dof)) if dof > 0 else None}


def numeric_cov(fun: Callable[[NDArray[np.float64]], NDArray[np.float64]], p: NDArray[np.float64], scales: NDArray[np.float64],
                s2: float) -> NDArray[np.float64]:
    """Gauss-Newton covariance s²(JᵀJ)⁻¹ of parameters p of a residual function (scaled for conditioning)."""
    return jacobian_cov(central_jacobian(fun, p, scales), scales, s2)


def jacobian_cov(J: NDArray[np.float64], scales: NDArray[np.float64], s2: float) -> NDArray[np.float64]:
    """s²(JᵀJ)⁻¹ from the residuals' Jacobian J (unscaled), scaled by `scales` for conditioning."""
    J = J * scales
    sv = np.linalg.svd(J, compute_uv=False)
    if sv[-1] <= 1e-10 * sv[0]:
        raise DegenerateDataError("the points do not determine every parameter of the model (singular fit)")
    cov: NDArray[np.float64] = np.linalg.inv(J.T @ J) * np.outer(scales, scales) * s2
    return cov


def uncertain_correct(f: Callable[[NDArray[np.float64], Mapping[str, NDArray[np.float64]]], NDArray[np.float64]], p: NDArray[np.float64],
                      cov: NDArray[np.float64] | None, data: Columns, sigma_deg: float,
                      dof: float) -> dict[str, NDArray[np.float64]]:
    """tilt = f(p, readings) and its expanded GUM uncertainty from cov and the reading noise.

    Covariance and reading noise come from one fit with `dof` degrees of freedom; the coverage
    factor follows from the Welch-Satterthwaite effective degrees of freedom (95 %).
    """
    inputs = {c: np.asarray(data[c], dtype=float) for c in MEAS_COLUMNS}
    y = f(p, inputs)
    out = {"tilt_x_deg": y[:, 0], "tilt_y_deg": y[:, 1]}
    if cov is not None:
        gum = propagate_gum(f, p, cov, inputs, {c: sigma_deg for c in MEAS_COLUMNS}, dof, dof)
        U, k = gum.expanded(), np.broadcast_to(coverage_factor(gum.dof_eff), gum.u.shape)
        out["u_tilt_x_deg"], out["u_tilt_y_deg"] = U[:, 0], U[:, 1]
        out[K_OUTPUTS[0]], out[K_OUTPUTS[1]] = k[:, 0], k[:, 1]
    return out


def meas_dof(model: CalibrationModel) -> float:
    """Degrees of freedom of the measurement-sensor fit (infinite for models written before it was kept)."""
    dof = model.state.get("meas_dof")
    return float(dof) if dof else float("inf")


def stage_commands(model: CalibrationModel, x: NDArray[np.float64], y: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
    """Levelling output of every stage method: refused where the bench cannot go.

    The travel is the bench's the model was fitted for (the kinematic model keeps it), else the
    stacked bench of docs/models.md §2 (±15°).
    """
    travel = float(model.state.get("bench", {}).get("travel_deg", StageBench().travel_deg))
    bad = ~(np.isfinite(x) & np.isfinite(y))
    if bad.any():
        rows = ", ".join(str(i + 1) for i in np.flatnonzero(bad)[:5])
        raise InputError(f"target row(s) {rows}: no stage angles reach the wanted tilt under this model")
    beyond = np.flatnonzero((np.abs(x) > travel) | (np.abs(y) > travel))
    if beyond.size:
        rows = ", ".join(str(i + 1) for i in beyond[:5])
        raise InputError(f"target row(s) {rows} need stage angles beyond the bench's travel of ±{travel:g} deg "
                         f"(e.g. stage_x_deg {x[beyond[0]]:.3f}, stage_y_deg {y[beyond[0]]:.3f})")
    return {"stage_x_deg": x, "stage_y_deg": y}


def targets(data: Columns) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    x, y = columns(data, ("target_x_deg", "target_y_deg"))
    return x, y


def stage_model(method: str, used: list[str], params: dict[str, Parameter], notes: list[str], **kw: Any) -> CalibrationModel:
    return CalibrationModel(kind="stage", method=method, columns=used, parameters=params, notes=notes, **kw)


def used_columns(data: Columns) -> list[str]:
    return [c for c in FIT_REQUIRED + FIT_OPTIONAL if c in data]


class StageMethod:
    """A stage calibration: fit (data -> model), level (wanted tilt -> stage commands), correct (readings -> tilt).

    Subclasses give `fit`, `commands` (the unchecked stage angles for the targets) and `correct`;
    levelling's checks (reachable, within the bench's travel) are the same for every method.
    """

    kind = "stage"
    name = ""
    fit_required = FIT_REQUIRED
    fit_optional = FIT_OPTIONAL
    correct_required = MEAS_COLUMNS
    correct_optional = ()
    outputs = TILT_OUTPUTS

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel:
        raise NotImplementedError

    def commands(self, model: CalibrationModel, data: Columns) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Stage angles for the targets in `data`, before levelling's checks."""
        raise NotImplementedError

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, NDArray[np.float64]]:
        raise NotImplementedError

    def level(self, model: CalibrationModel, data: Columns) -> dict[str, NDArray[np.float64]]:
        x, y = self.commands(model, data)
        return stage_commands(model, x, y)
