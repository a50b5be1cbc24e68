"""Seed 000 ref. [9] as seed 000 describes it: the off-axis coupling model alone (one gain
kappa)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from service.calibration.methods.stage.base import (
    FIT_REQUIRED,
    Columns,
    StageMethod,
    bench_state,
    fit_stats,
    meas_dof,
    meas_sign,
    stage_hardware,
    stage_model,
    targets,
    used_columns,
)
from service.calibration.methods.stage.common import (
    MEAS_COLUMNS,
    columns,
    has_meas,
    mirror_note,
    model_needs_meas,
    newton_2d,
    require_spread,
)
from service.calibration.model import CalibrationModel, ModelState, Parameter, residual_summary
from service.calibration.registry import FitOptions
from service.calibration.uncertainty import coverage_factor
from service.errors import DegenerateDataError
from service.io.columns import K_OUTPUTS
from service.physics.stage import offaxis_error_deg, offaxis_inverse_deg


def _prediction_bound(sizes: NDArray[np.float64], coverage: float = 0.95) -> float:
    """The ⌈p (n + 1)⌉-th smallest of n sizes: a new point's size from the same range lies below
    it with probability at least p, whatever their distribution (the largest where n is small)."""
    ordered = np.sort(sizes)
    rank = min(int(np.ceil(coverage * (ordered.size + 1))), ordered.size)
    return float(ordered[rank - 1])


class CouplingMethod(StageMethod):
    """Ref. [9] as seed 000 describes it: the off-axis coupling model alone, no linear installation
    errors.

    Reading: the reference reads X = x - κ·error10(x, y), Y = y (κ = 1 is the bare geometry of eq.
    9); calibration fits κ. The measurement sensor, by the same assumption, reads the table tilt
    directly (only an upside-down mounting, detected from the data, is undone): that is its H2-like
    step.
    """

    name = "coupling"

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel:
        sx, sy, rx, ry = columns(data, FIT_REQUIRED)
        require_spread(sx, sy, 3, "the coupling model")
        err10 = offaxis_error_deg(sx, sy)
        if float(err10 @ err10) < 1e-12:
            raise DegenerateDataError(
                "the coupling model needs points with both stages away from zero (off the "
                "θx = 0 and θy = 0 lines), where eq. (10)'s error is not zero"
            )
        diff = sx - rx
        kappa = float(err10 @ diff / (err10 @ err10))
        res = {"ref_x_deg": (sx - kappa * err10) - rx, "ref_y_deg": sy - ry}
        all_res = np.concatenate(list(res.values()))
        st = fit_stats(all_res, 1)
        var_k = float(np.sum(res["ref_x_deg"] ** 2) / max(sx.size - 1, 1) / (err10 @ err10))
        params = {
            "offaxis_coupling.kappa": Parameter(
                kappa,
                "1",
                note="x reading = x - kappa * eq.(10) error; 1 is the bare stacked-stage geometry",
            )
        }
        notes = [
            (
                "ref. [9] as read from seed 000 §0 and §4.5: the nonlinear coupling between the "
                "two tilt axes (the same as eq. 10) and nothing else; no zero offsets, yaws, "
                "scales or mounting tilts, so those installation errors stay in the levelled "
                "and corrected values"
            ),
            (
                "levelling: y = Y, and x solves x - kappa * error10(x, y) = X (exact for kappa "
                "= 1: x = asin(sin X / cos Y))"
            ),
        ]
        state: ModelState = {
            "has_meas": has_meas(data),
            **bench_state(*stage_hardware(options)[:2]),
        }
        if has_meas(data):
            sign, how = meas_sign(data, options)
            state["meas_sign"] = sign.tolist()
            mx, my = columns(data, MEAS_COLUMNS)
            res.update({"meas_x_deg": sign[0] * mx - rx, "meas_y_deg": sign[1] * my - ry})
            state["meas_misfit_rms_deg"] = [
                float(np.sqrt(np.mean(res[column] ** 2))) for column in ("meas_x_deg", "meas_y_deg")
            ]
            state["meas_dof"] = int(mx.size)  # an RMS over the points, nothing fitted
            # the installation error left is a fixed function of the pose, not noise: U is a
            # distribution-free 95 % bound on its size over the calibrated range (k × the RMS would
            # hold every point)
            state["meas_misfit_p95_deg"] = [
                _prediction_bound(np.abs(res[column])) for column in ("meas_x_deg", "meas_y_deg")
            ]
            # beyond the calibrated range the misfit (installation errors: offsets and small
            # rotations, near-linear in the tilt) keeps growing at its slope over the range
            design = np.column_stack([np.ones_like(rx), rx, ry])
            state["meas_misfit_slope"] = [
                np.abs(np.linalg.lstsq(design, res[column], rcond=None)[0][1:]).tolist()
                for column in ("meas_x_deg", "meas_y_deg")
            ]
            state["meas_misfit_range_deg"] = {
                "x": [float(rx.min()), float(rx.max())],
                "y": [float(ry.min()), float(ry.max())],
            }
            notes.append(
                "this model cannot describe the measurement sensor: its H2-like step takes the "
                "measurement reading as the table tilt (the model has no installation errors); "
                "the meas_* residuals show what that leaves, and the expanded uncertainty is a "
                "distribution-free 95 % bound on their size over the points, the "
                "ceil(0.95 (n + 1))-th smallest, grown beyond the calibrated range at their slope "
                "(the unmodelled installation error, a fixed function of the pose, taken as an "
                "uncertainty, not a GUM propagation); the standard uncertainty is their RMS"
            )
            if (mn := mirror_note(sign)) is not None:
                notes.append(f"{mn} ({how})")
        return stage_model(
            self.name,
            used_columns(data),
            params,
            notes,
            covariance_names=["offaxis_coupling.kappa"],
            covariance=np.array([[var_k]]),
            residuals=residual_summary(res, "deg"),
            fit={"n_points": int(sx.size), **st},
            state=state,
        )

    def commands(
        self, model: CalibrationModel, data: Columns
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        tx, ty = targets(data)
        k = model.value("offaxis_coupling.kappa")
        x0 = offaxis_inverse_deg(tx, ty, clip=True)
        x, y = newton_2d(lambda u, v: (u - k * offaxis_error_deg(u, v), v), tx, ty, x0, ty.copy())
        return x, y

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, NDArray[np.float64]]:
        model_needs_meas(model)
        sign = np.asarray(model.state.get("meas_sign", [1.0, 1.0]), dtype=float)
        mx, my = columns(data, MEAS_COLUMNS)
        ux, uy = model.state.get("meas_misfit_rms_deg", [0.0, 0.0])
        k = float(coverage_factor(meas_dof(model)))
        # models made before the bound was kept: k × the RMS, as they were
        px, py = model.state.get("meas_misfit_p95_deg", [k * ux, k * uy])
        tilt_x, tilt_y = sign[0] * mx, sign[1] * my
        expanded_x, expanded_y = np.full(mx.shape, px), np.full(my.shape, py)
        seen = model.state.get("meas_misfit_range_deg")
        slopes = model.state.get("meas_misfit_slope")
        if seen is not None and slopes is not None:
            # how far each reading lies beyond the calibrated range, per axis
            beyond = [
                np.maximum(0.0, np.maximum(tilt - seen[axis][1], seen[axis][0] - tilt))
                for axis, tilt in (("x", tilt_x), ("y", tilt_y))
            ]
            expanded_x = expanded_x + slopes[0][0] * beyond[0] + slopes[0][1] * beyond[1]
            expanded_y = expanded_y + slopes[1][0] * beyond[0] + slopes[1][1] * beyond[1]
        return {
            "tilt_x_deg": tilt_x,
            "tilt_y_deg": tilt_y,
            "u_tilt_x_deg": expanded_x,
            "u_tilt_y_deg": expanded_y,
            K_OUTPUTS[0]: expanded_x / ux if ux > 0 else np.full(mx.shape, k),
            K_OUTPUTS[1]: expanded_y / uy if uy > 0 else np.full(my.shape, k),
        }


COUPLING = CouplingMethod()
