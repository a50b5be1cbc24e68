"""Seed 000: two homographies (H1 reference -> stage, H2 measurement -> reference) and eq. (10)'s
off-axis compensation of the upper stage."""

from __future__ import annotations

from collections.abc import Mapping
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.calibration.methods.stage.base import (
    CROSS_TOL_DEG,
    FIT_REQUIRED,
    Columns,
    StageMethod,
    ThreeWay,
    bench_state,
    fit_stats,
    jacobian_cov,
    meas_dof,
    meas_reading_noise,
    noise_state,
    reading_noise_of,
    stage_hardware,
    stage_model,
    targets,
    uncertain_correct,
    used_columns,
)
from service.calibration.methods.stage.common import (
    MEAS_COLUMNS,
    columns,
    detect_mirror,
    has_meas,
    model_needs_meas,
    offaxis_forward_vs_exact_deg,
    offaxis_paper_forward_deg,
)
from service.calibration.model import (
    CalibrationModel,
    FitInfo,
    ModelState,
    Parameter,
    residual_summary,
)
from service.calibration.projective import apply_projective, fit_projective, transfer_residuals
from service.calibration.registry import FitOptions
from service.errors import DegenerateDataError, InputError
from service.physics.stage import offaxis_inverse_deg, offaxis_reading_deg

H_UNITS = {
    "h11": "1",
    "h12": "1",
    "h13": "deg",
    "h21": "1",
    "h22": "1",
    "h23": "deg",
    "h31": "1/deg",
    "h32": "1/deg",
}
H_KEYS = tuple(H_UNITS)
H_SCALES = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1e-2, 1e-2])


def _h_params(prefix: str, H: NDArray[np.float64], note: str = "") -> dict[str, Parameter]:
    return {
        f"{prefix}.{k}": Parameter(float(value), H_UNITS[k], note=note if k == "h11" else "")
        for k, value in zip(H_KEYS, H.ravel()[:8])
    }


def _h_of(model: CalibrationModel, prefix: str) -> NDArray[np.float64]:
    return np.append(model.values([f"{prefix}.{k}" for k in H_KEYS]), 1.0).reshape(3, 3)


@lru_cache(maxsize=1)
def _forward_vs_exact() -> dict[str, float]:
    """The same for every fit (a fixed grid): computed once."""
    return offaxis_forward_vs_exact_deg()


def _apply_h(
    h8: NDArray[np.float64], x: ArrayLike, y: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    return apply_projective(np.append(h8, 1.0).reshape(3, 3), x, y)


def _check_options(points: Any, offaxis: Any) -> None:
    """Refuse an unknown `points` or `offaxis` option, naming the choices."""
    if points not in ("cross", "all"):
        raise InputError(f"option points: {points!r} is not one of cross, all")
    if offaxis not in ("exact", "paper"):
        raise InputError(f"option offaxis: {offaxis!r} is not one of exact, paper")


def _h1_points(
    sx: NDArray[np.float64], sy: NDArray[np.float64], points: str
) -> tuple[NDArray[np.bool_], str, list[str]]:
    """The points H1 is fitted on (the cross unless it is unusable, or all), in words, and notes."""
    notes = []
    cross = (np.abs(sx) < CROSS_TOL_DEG) | (np.abs(sy) < CROSS_TOL_DEG)
    use = cross if points == "cross" else np.ones_like(cross)
    used_what = "the cross (points with stage_x_deg = 0 or stage_y_deg = 0)"
    if points == "cross":
        on_x = np.unique(np.round(sx[cross & (np.abs(sy) < CROSS_TOL_DEG)], 6))
        on_y = np.unique(np.round(sy[cross & (np.abs(sx) < CROSS_TOL_DEG)], 6))
        if on_x.size < 3 or on_y.size < 3:
            use = np.ones_like(cross)
            used_what = (
                "all points (the data have no usable cross: fewer than 3 stage angles "
                "on a zero line)"
            )
            notes.append(
                "H1: the data lack the cross seed 000 recommends (points on the θx = 0 and θy "
                "= 0 lines); "
                "fitted on all points with the stage x angles decoupled by eq. (9) instead"
            )
    else:
        used_what = (
            "all points, stage x decoupled by eq. (9) (x' = asin(sin x cos y)) before the DLT"
        )
    return use, used_what, notes


def _check_reachable(cmd_x: NDArray[np.float64]) -> None:
    """Refuse an H1 that sends a reference reading to an x angle no upper-stage command reaches."""
    unreachable = np.flatnonzero(~np.isfinite(cmd_x))
    if unreachable.size:
        rows = ", ".join(str(i + 1) for i in unreachable[:5])
        raise DegenerateDataError(
            f"H1 maps the reference reading of row(s) {rows} to an x angle no upper-stage "
            "command reaches (|sin x' / cos y| > 1): the homography does not describe "
            "these points; calibrate over a range the stages can level"
        )


class HomographyMethod(StageMethod):
    """Seed 000: H1 (reference -> stage, eq. 11) and H2 (measurement -> reference) by normalised
    DLT, then eq. (10)'s off-axis compensation of the upper stage, applied as its exact inverse."""

    name = "homography"

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel:
        sx, sy, rx, ry = columns(data, FIT_REQUIRED)
        points = options.extra.get("points", "cross")
        offaxis = options.extra.get("offaxis", "exact")
        _check_options(points, offaxis)
        use, used_what, notes = _h1_points(sx, sy, points)
        # x' = asin(sin x cos y): the x reading an uncoupled bench would give; on the cross x' = x
        # exactly.
        xd = offaxis_reading_deg(sx, sy)
        H1 = fit_projective(rx[use], ry[use], xd[use], sy[use], what="H1 (reference -> stage)")
        px, py = apply_projective(H1, rx, ry)
        res_h1 = {"stage_x_deg": px[use] - xd[use], "stage_y_deg": py[use] - sy[use]}
        # the whole levelling model on every point: command predicted from the reference reading
        cmd_x = (
            offaxis_inverse_deg(px, py) if offaxis == "exact" else offaxis_paper_forward_deg(px, py)
        )
        _check_reachable(cmd_x)
        level_res = {"stage_x_deg": cmd_x - sx, "stage_y_deg": py - sy}
        fwd = dict(_forward_vs_exact())
        notes += [
            (
                "H1 (reference -> stage angles, seed 000 eq. 11) fitted by normalised DLT on "
                f"{int(use.sum())} points: {used_what}. Seed 000 §3: on those lines eq. (10)'s "
                "error vanishes, so H1 sees only the near-linear installation errors"
            ),
            "levelling = H1 then eq. (10) for the upper stage: H1 gives (x', y) with x' the "
            "angle an uncoupled upper stage would need; the command is x = asin(sin x' / cos "
            "y), the exact inverse of eq. (9)"
            + (
                " (option offaxis=paper: x = x' + error(x', y) as seed 000 prints it)"
                if offaxis == "paper"
                else ""
            ),
            (
                f"eq. (10) applied forwards (x' + error) differs from the exact inverse by up to "
                f"{fwd['max_abs_command_difference_deg']:.4f} deg (rms "
                f"{fwd['rms_command_difference_deg']:.4f}) on the "
                f"±12 deg grid, largest at x' = {fwd['at_x_deg']:g}, y = {fwd['at_y_deg']:g}"
            ),
        ]
        params = _h_params(
            "H1", H1, "H1 maps reference angles (X, Y) to stage angles (x', y), h33 = 1"
        )
        residuals = dict(res_h1)
        fit_info: FitInfo = {
            "n_points": int(sx.size),
            "n_points_h1": int(use.sum()),
            "points": points,
            "offaxis": offaxis,
            "h1": fit_stats(np.concatenate(list(res_h1.values())), 8),
            "levelling_residual_all_points": residual_summary(level_res, "deg", False),
            "offaxis_forward_vs_exact": fwd,
        }
        cov = None
        cov_names: list[str] = []
        state: ModelState = {
            "has_meas": has_meas(data),
            "offaxis": offaxis,
            **bench_state(*stage_hardware(options)[:2]),
        }
        if has_meas(data):
            mx, my = columns(data, MEAS_COLUMNS)
            # Two sensors on one table: no stage coupling between them, so every point serves H2.
            H2 = fit_projective(mx, my, rx, ry, what="H2 (measurement -> reference)")
            h2 = H2.ravel()[:8]

            res_h2, J2 = transfer_residuals(h2, mx, my, rx, ry)
            st = fit_stats(res_h2, 8)
            params.update(
                _h_params(
                    "H2", H2, "H2 maps measurement readings (a, b) to reference angles (X, Y)"
                )
            )
            n = mx.size
            residuals.update({"ref_x_deg": res_h2[:n], "ref_y_deg": res_h2[n:]})
            fit_info["h2"] = st
            h2_note = (
                f"H2 (measurement -> reference) fitted by normalised DLT on all {n} points: both "
                "sensors ride on the table, so the stage coupling does not enter between them; "
            )
            if st["sigma_deg"] is not None:
                cov = jacobian_cov(J2, H_SCALES, st["sigma_deg"] ** 2)
                cov_names = [f"H2.{k}" for k in H_KEYS]
                # the three instruments at every point: H2(meas) − ref in the reference's frame,
                # H1(ref) − the stage's angles (x decoupled) in the stage's
                three_way = ThreeWay(
                    np.array([res_h2[:n], res_h2[n:]]), np.array([px - xd, py - sy])
                )
                noise = meas_reading_noise(
                    data,
                    options,
                    st["sigma_deg"],
                    st["dof"],
                    detect_mirror(mx, my, rx, ry),
                    three_way,
                )
                state["meas_sigma_deg"] = st["sigma_deg"]
                state["meas_dof"] = st["dof"]
                state.update(noise_state(noise))
                notes.append(
                    h2_note
                    + "the uncertainty of a corrected tilt from H2's covariance and the reading "
                    f"noise of one measurement reading, {noise.sigma_deg:.3g} deg: {noise.source}"
                )
            else:
                notes.append(
                    h2_note
                    + f"the {n} points determine its 8 parameters exactly and leave no residual to "
                    "estimate the noise: no covariance and no u_tilt"
                )
        else:
            notes.append(
                "no meas_x_deg/meas_y_deg columns: H2 not fitted, this model can level but not "
                "correct"
            )
        return stage_model(
            self.name,
            used_columns(data),
            params,
            notes,
            covariance_names=cov_names,
            covariance=cov,
            residuals=residual_summary(residuals, "deg"),
            fit=fit_info,
            state=state,
            options={"points": points, "offaxis": offaxis},
        )

    def commands(
        self, model: CalibrationModel, data: Columns
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        tx, ty = targets(data)
        xd, y = apply_projective(_h_of(model, "H1"), tx, ty)
        if model.state.get("offaxis", "exact") == "paper":
            x = offaxis_paper_forward_deg(xd, y)
        else:
            x = offaxis_inverse_deg(xd, y)
        return x, y

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, NDArray[np.float64]]:
        model_needs_meas(model)
        names = [f"H2.{k}" for k in H_KEYS]

        def f(
            p: NDArray[np.float64], inp: Mapping[str, NDArray[np.float64]]
        ) -> NDArray[np.float64]:
            tilt_x, tilt_y = _apply_h(p, inp["meas_x_deg"], inp["meas_y_deg"])
            return np.column_stack([tilt_x, tilt_y])

        sigma, noise_dof = reading_noise_of(model)
        return uncertain_correct(
            f, model.values(names), model.cov_of(names), data, sigma, meas_dof(model), noise_dof
        )


HOMOGRAPHY = HomographyMethod()
