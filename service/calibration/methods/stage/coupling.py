"""Seed 000 ref. [9] as seed 000 describes it: the off-axis coupling model alone (one gain
kappa)."""

from __future__ import annotations

from dataclasses import dataclass

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


@dataclass(frozen=True)
class MisfitEnvelope:
    """How large the misfit one axis is left with is expected to be at a pose: |plane| + scatter,
    and the bound and RMS of the points' |misfit| relative to it."""

    plane: list[float]  # a, b, c of a + b·X + c·Y (degrees, degrees per degree)
    scatter_deg: float  # the misfit's RMS about the plane (n − 3 degrees of freedom)
    score_p95: float
    score_rms: float

    def at(self, tilt_x: NDArray[np.float64], tilt_y: NDArray[np.float64]) -> NDArray[np.float64]:
        a, b, c = self.plane
        return np.abs(a + b * tilt_x + c * tilt_y) + self.scatter_deg


def _misfit_envelope(
    x: NDArray[np.float64], y: NDArray[np.float64], misfit: NDArray[np.float64]
) -> MisfitEnvelope:
    design = np.column_stack([np.ones_like(x), x, y])
    plane = np.linalg.lstsq(design, misfit, rcond=None)[0]
    left = misfit - design @ plane
    scatter = float(np.sqrt(left @ left / max(misfit.size - 3, 1)))
    shape = MisfitEnvelope([float(v) for v in plane], scatter, 1.0, 1.0)
    envelope = shape.at(x, y)
    if not np.all(envelope > 0):  # a misfit that is exactly a plane through zero: nothing left
        envelope = np.maximum(envelope, np.finfo(float).tiny)
    score = np.abs(misfit) / envelope
    return MisfitEnvelope(
        shape.plane,
        scatter,
        _prediction_bound(score),
        float(np.sqrt(np.mean(score**2))),
    )


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
            # the installation error left is a fixed function of the pose, not noise: near-linear
            # in the tilt (offsets and small rotations), so its size follows an envelope over the
            # pose, |a + b·X + c·Y| plus the scatter about that plane; U is a distribution-free
            # 95 % bound on |misfit| / envelope over the points, times the envelope where a
            # reading lies (one bound for the whole range would hold the middle and miss the edges)
            envelopes = [_misfit_envelope(rx, ry, res[column]) for column in MEAS_COLUMNS]
            state["meas_misfit_plane_deg"] = [e.plane for e in envelopes]
            state["meas_misfit_scatter_deg"] = [e.scatter_deg for e in envelopes]
            state["meas_misfit_score_p95"] = [e.score_p95 for e in envelopes]
            state["meas_misfit_score_rms"] = [e.score_rms for e in envelopes]
            notes.append(
                "this model cannot describe the measurement sensor: its H2-like step takes the "
                "measurement reading as the table tilt (the model has no installation errors); "
                "the meas_* residuals show what that leaves; their size follows an envelope over "
                "the pose (|a + b X + c Y| fitted to them, plus their scatter about that plane), "
                "and the expanded uncertainty is the envelope times a distribution-free 95 % "
                "bound on |residual| / envelope over the points (the ceil(0.95 (n + 1))-th "
                "smallest), the standard uncertainty the envelope times their RMS: the unmodelled "
                "installation error, a fixed function of the pose, taken as an uncertainty, not a "
                "GUM propagation"
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
        tilt_x, tilt_y = sign[0] * mx, sign[1] * my
        planes = model.state.get("meas_misfit_plane_deg")
        if planes is not None:
            envelopes = [
                MisfitEnvelope(
                    planes[axis],
                    model.state["meas_misfit_scatter_deg"][axis],
                    model.state["meas_misfit_score_p95"][axis],
                    model.state["meas_misfit_score_rms"][axis],
                )
                for axis in (0, 1)
            ]
            at = [e.at(tilt_x, tilt_y) for e in envelopes]
            # a misfit of exactly nothing (a bench the model represents, without noise): U = 0,
            # its k the one of the points' degrees of freedom
            ks = [
                e.score_p95 / e.score_rms if e.score_rms > 0 else coverage_factor(meas_dof(model))
                for e in envelopes
            ]
            return {
                "tilt_x_deg": tilt_x,
                "tilt_y_deg": tilt_y,
                "u_tilt_x_deg": envelopes[0].score_p95 * at[0],
                "u_tilt_y_deg": envelopes[1].score_p95 * at[1],
                K_OUTPUTS[0]: np.full(mx.shape, float(ks[0])),
                K_OUTPUTS[1]: np.full(my.shape, float(ks[1])),
            }
        k = float(coverage_factor(meas_dof(model)))
        # models made before the envelope: one bound per axis grown beyond the range at the
        # misfit's slope; before the bound, k × the RMS
        px, py = model.state.get("meas_misfit_p95_deg", [k * ux, k * uy])
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
