"""The uncertainty budget a new record keeps (service.calibration.budget): gathered from the fit,
the calibration points, the reference standards the job named and the sensors' resolution."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from service.calibration.budget import (
    ReferenceStandard,
    UncertaintyBudget,
    current_names,
    model_dof,
    record_budget,
)
from service.calibration.model import CalibrationModel
from service.calibration.uncertainty import COVERAGE, dof_of_coverage_factor
from service.io.columns import K_OUTPUTS

ROLE_WORDS = {"measurement_sensor": "measurement sensor", "reference_sensor": "reference sensor"}
NOT_TRACEABLE = "no reference standard: not traceable"


def with_traceability(budget: Mapping[str, object] | None) -> UncertaintyBudget | None:
    """The budget saying whether a reference standard's uncertainty is in it: one without a standard
    says "no reference standard: not traceable" (such a record gets no certificate)."""
    budget = current_names(budget)
    if budget is None:
        return None
    traceable = any(
        component.get("source") == "reference_standard"
        for component in budget.get("components") or []
    )
    out = cast(
        UncertaintyBudget,
        {key: value for key, value in budget.items() if key not in ("traceable", "warning")},
    )
    out["traceable"] = traceable
    if not traceable:
        out["warning"] = NOT_TRACEABLE
    return out


def resolutions_deg(bench: Any) -> dict[str, float | None]:
    """Each sensor's output resolution (degrees) as its driver states it; None where it states
    none."""
    out: dict[str, float | None] = {}
    for role in bench.devices:
        # only a tilt sensor's protocol states its resolution
        sensor = bench.devices.tilt_sensor(role)
        resolution = sensor.resolution_deg if sensor is not None else None
        out[role] = (
            float(resolution) if isinstance(resolution, int | float) and resolution > 0 else None
        )
    return out


def budget_of_record(
    method: Any,
    model: CalibrationModel,
    fit_columns: Mapping[str, NDArray[np.float64]] | None,
    standards: Sequence[ReferenceStandard],
    resolutions: Mapping[str, float | None],
) -> UncertaintyBudget:
    """The record's budget; the corrected tilt's entries where the method corrects readings (stage
    records)."""
    model_json = model.to_json_dict()
    dof = model_dof(model_json)
    parameter_u = {name: std for name in model.parameters if (std := model.std(name)) is not None}
    tilt_u = tilt_dof = temps = errors = None
    if fit_columns is not None and method.kind == "stage" and "meas_x_deg" in fit_columns:
        out = method.correct(model, fit_columns)
        if "u_tilt_x_deg" in out:
            tilt_u, tilt_dof = _corrected_tilt_u(out)
        if "temp_c" in fit_columns:
            temps = np.asarray(fit_columns["temp_c"], dtype=float)
            errors = _fit_errors(out, fit_columns)
    budget = record_budget(
        parameters=model_json.get("parameters") or {},
        parameter_u=parameter_u,
        dof_fit=dof,
        standards=standards,
        resolutions_deg=_resolution_words(resolutions),
        tilt_u_fit_deg=tilt_u,
        tilt_dof_fit=tilt_dof,
        temps_c=temps,
        errors_deg=errors,
    )
    return with_traceability(budget) or budget


def _resolution_words(resolutions: Mapping[str, float | None]) -> dict[str, float | None]:
    """The sensors' resolutions as the budget names them ("measurement sensor"), other roles
    left out."""
    return {
        ROLE_WORDS.get(role, role.replace("_", " ")): resolution
        for role, resolution in resolutions.items()
        if role in ROLE_WORDS or role.endswith("_sensor")
    }


def _corrected_tilt_u(
    out: Mapping[str, NDArray[np.float64]],
) -> tuple[tuple[float, float], tuple[float, float]]:
    """The fit's part of a corrected tilt per axis (x, y): its standard uncertainty (RMS over the
    fit points of the expanded one over its coverage factor) and the fewest degrees of freedom that
    coverage factor stands for."""
    u_fit, nus = [], []
    for axis, key in (("x", K_OUTPUTS[0]), ("y", K_OUTPUTS[1])):
        coverage_k = np.asarray(out[key], dtype=float)
        u_axis = np.asarray(out[f"u_tilt_{axis}_deg"], dtype=float) / coverage_k
        u_fit.append(float(np.sqrt(np.mean(u_axis**2))))
        nus.append(float(np.min(dof_of_coverage_factor(coverage_k, COVERAGE))))
    return (u_fit[0], u_fit[1]), (nus[0], nus[1])


def _fit_errors(
    out: Mapping[str, NDArray[np.float64]], fit_columns: Mapping[str, NDArray[np.float64]]
) -> NDArray[np.float64]:
    """The corrected tilts less the reference's at the fit points, (points, 2): what the budget
    judges a temperature dependence by."""
    return np.column_stack(
        [
            out["tilt_x_deg"] - fit_columns["ref_x_deg"],
            out["tilt_y_deg"] - fit_columns["ref_y_deg"],
        ]
    )
