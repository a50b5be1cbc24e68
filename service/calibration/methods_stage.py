"""Stage calibration methods (kind `stage`): homography (seed 000), coupling (its ref. [9]),
axis-transform (its ref. [10]) and kinematic (the full chain of spec §2).

Every method levels (wanted table tilt -> stage commands) and corrects (measurement-sensor
reading -> table tilt). The readings of refs. [9] and [10] are written out in
docs/calibration-stage.md and in each model's notes.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from service.calibration.benchfit import StagePoints, param_label
from service.calibration.model import CalibrationModel, Parameter, residual_summary
from service.calibration.projective import apply_projective, fit_projective
from service.calibration.registry import FitOptions, register
from service.calibration.stage_common import (
    LEVEL_OUTPUTS,
    MEAS_COLUMNS,
    MEAS_NAMES,
    MEAS_PARAMS,
    REF_COLUMNS,
    STAGE_COLUMNS,
    TILT_OUTPUTS,
    check_loss,
    columns,
    decouple_x_deg,
    detect_mirror,
    has_meas,
    meas_inverse_with_u,
    mirror_note,
    model_needs_meas,
    newton_2d,
    offaxis_error_deg,
    offaxis_exact_inverse_deg,
    offaxis_forward_vs_exact_deg,
    offaxis_paper_forward_deg,
    require_spread,
    sign_from_options,
)
from service.calibration.stage_kinematic import ChainModel, fit_chain, fit_meas, unit_of
from service.calibration.uncertainty import expanded, propagate
from service.errors import DegenerateDataError, InputError
from service.physics.stage import StageBench

Columns = Mapping[str, np.ndarray]
FIT_REQUIRED = STAGE_COLUMNS + REF_COLUMNS
FIT_OPTIONAL = MEAS_COLUMNS + ("dir_x", "dir_y", "temp_c", "t_s", "point")
CROSS_TOL_DEG = 1e-6


def _meas_sign(data: Columns, options: FitOptions) -> tuple[np.ndarray, str]:
    mx, my, rx, ry = columns(data, MEAS_COLUMNS + REF_COLUMNS)
    return sign_from_options(options.extra, detect_mirror(mx, my, rx, ry))


def _stats(r: np.ndarray, n_par: int) -> dict[str, Any]:
    """Degrees of freedom and residual sigma; no sigma when the points only just determine the parameters."""
    dof = r.size - n_par
    return {"dof": dof, "sigma_deg": float(np.sqrt(r @ r / dof)) if dof > 0 else None}


def _numeric_cov(fun, p: np.ndarray, scales: np.ndarray, s2: float) -> np.ndarray:
    """Gauss-Newton covariance s²(JᵀJ)⁻¹ of parameters p of a residual function (scaled for conditioning)."""
    cols = []
    for i in range(p.size):
        h = 1e-6 * max(abs(p[i]), scales[i])
        e = np.zeros_like(p)
        e[i] = h
        cols.append((fun(p + e) - fun(p - e)) / (2 * h))
    J = np.column_stack(cols) * scales
    sv = np.linalg.svd(J, compute_uv=False)
    if sv[-1] <= 1e-10 * sv[0]:
        raise DegenerateDataError("the points do not determine every parameter of the model (singular fit)")
    return np.linalg.inv(J.T @ J) * np.outer(scales, scales) * s2


def _uncertain_correct(f, p: np.ndarray, cov: np.ndarray | None, data: Columns, sigma_deg: float) -> dict[str, np.ndarray]:
    """tilt = f(p, readings) and its expanded (k = 2) GUM uncertainty from cov and the reading noise."""
    inputs = {c: np.asarray(data[c], dtype=float) for c in MEAS_COLUMNS}
    y = f(p, inputs)
    out = {"tilt_x_deg": y[:, 0], "tilt_y_deg": y[:, 1]}
    if cov is not None:
        u = propagate(f, p, cov, inputs, {c: sigma_deg for c in MEAS_COLUMNS})
        U = expanded(u)
        out["u_tilt_x_deg"], out["u_tilt_y_deg"] = U[:, 0], U[:, 1]
    return out


def stage_commands(model: CalibrationModel, x: np.ndarray, y: np.ndarray) -> dict[str, np.ndarray]:
    """Levelling output of every stage method: refused where the bench cannot go.

    The travel is the bench's the model was fitted for (the kinematic model keeps it), else the
    stacked bench of spec/models.md §2 (±15°).
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


def _targets(data: Columns) -> tuple[np.ndarray, np.ndarray]:
    return tuple(columns(data, ("target_x_deg", "target_y_deg")))  # type: ignore[return-value]


def _model(method: str, used: list[str], params: dict[str, Parameter], notes: list[str], **kw) -> CalibrationModel:
    return CalibrationModel(kind="stage", method=method, columns=used, parameters=params, notes=notes, **kw)


def _used_columns(data: Columns) -> list[str]:
    return [c for c in FIT_REQUIRED + FIT_OPTIONAL if c in data]


# --- homography (seed 000) --------------------------------------------------------------------
H_UNITS = {"h11": "1", "h12": "1", "h13": "deg", "h21": "1", "h22": "1", "h23": "deg", "h31": "1/deg", "h32": "1/deg"}
H_KEYS = tuple(H_UNITS)
H_SCALES = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1e-2, 1e-2])


def _h_params(prefix: str, H: np.ndarray, note: str = "") -> dict[str, Parameter]:
    return {f"{prefix}.{k}": Parameter(float(v), H_UNITS[k], note=note if k == "h11" else "")
            for k, v in zip(H_KEYS, H.ravel()[:8])}


def _h_of(model: CalibrationModel, prefix: str) -> np.ndarray:
    return np.append(model.values([f"{prefix}.{k}" for k in H_KEYS]), 1.0).reshape(3, 3)


def _apply_h(h8: np.ndarray, x, y) -> tuple[np.ndarray, np.ndarray]:
    return apply_projective(np.append(h8, 1.0).reshape(3, 3), x, y)


class HomographyMethod:
    """Seed 000: H1 (reference -> stage, eq. 11) and H2 (measurement -> reference) by normalised DLT,
    then eq. (10)'s off-axis compensation of the upper stage, applied as its exact inverse."""

    kind = "stage"
    name = "homography"
    fit_required = FIT_REQUIRED
    fit_optional = FIT_OPTIONAL
    correct_required = MEAS_COLUMNS
    correct_optional = ()
    outputs = TILT_OUTPUTS

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel:
        sx, sy, rx, ry = columns(data, FIT_REQUIRED)
        points = options.extra.get("points", "cross")
        offaxis = options.extra.get("offaxis", "exact")
        if points not in ("cross", "all"):
            raise InputError(f"option points: {points!r} is not one of cross, all")
        if offaxis not in ("exact", "paper"):
            raise InputError(f"option offaxis: {offaxis!r} is not one of exact, paper")
        notes = []
        cross = (np.abs(sx) < CROSS_TOL_DEG) | (np.abs(sy) < CROSS_TOL_DEG)
        use = cross if points == "cross" else np.ones_like(cross)
        used_what = "the cross (points with stage_x_deg = 0 or stage_y_deg = 0)"
        if points == "cross":
            on_x = np.unique(np.round(sx[cross & (np.abs(sy) < CROSS_TOL_DEG)], 6))
            on_y = np.unique(np.round(sy[cross & (np.abs(sx) < CROSS_TOL_DEG)], 6))
            if on_x.size < 3 or on_y.size < 3:
                use = np.ones_like(cross)
                used_what = "all points (the data have no usable cross: fewer than 3 stage angles on a zero line)"
                notes.append("H1: the data lack the cross seed 000 recommends (points on the θx = 0 and θy = 0 lines); "
                             "fitted on all points with the stage x angles decoupled by eq. (9) instead")
        else:
            used_what = "all points, stage x decoupled by eq. (9) (x' = asin(sin x cos y)) before the DLT"
        # x' = asin(sin x cos y): the x reading an uncoupled bench would give; on the cross x' = x exactly.
        xd = decouple_x_deg(sx, sy)
        H1 = fit_projective(rx[use], ry[use], xd[use], sy[use], what="H1 (reference -> stage)")
        px, py = apply_projective(H1, rx, ry)
        res_h1 = {"stage_x_deg": px[use] - xd[use], "stage_y_deg": py[use] - sy[use]}
        # the whole levelling model on every point: command predicted from the reference reading
        cmd_x = offaxis_exact_inverse_deg(px, py) if offaxis == "exact" else offaxis_paper_forward_deg(px, py)
        unreachable = np.flatnonzero(~np.isfinite(cmd_x))
        if unreachable.size:
            rows = ", ".join(str(i + 1) for i in unreachable[:5])
            raise DegenerateDataError(f"H1 maps the reference reading of row(s) {rows} to an x angle no upper-stage "
                                      "command reaches (|sin x' / cos y| > 1): the homography does not describe "
                                      "these points; calibrate over a range the stages can level")
        level_res = {"stage_x_deg": cmd_x - sx, "stage_y_deg": py - sy}
        fwd = offaxis_forward_vs_exact_deg()
        notes += [
            f"H1 (reference -> stage angles, seed 000 eq. 11) fitted by normalised DLT on {int(use.sum())} points: "
            f"{used_what}. Seed 000 §3: on those lines eq. (10)'s error vanishes, so H1 sees only the near-linear "
            "installation errors",
            "levelling = H1 then eq. (10) for the upper stage: H1 gives (x', y) with x' the angle an uncoupled "
            "upper stage would need; the command is x = asin(sin x' / cos y), the exact inverse of eq. (9)"
            + (" (option offaxis=paper: x = x' + error(x', y) as seed 000 prints it)" if offaxis == "paper" else ""),
            f"eq. (10) applied forwards (x' + error) differs from the exact inverse by up to "
            f"{fwd['max_abs_command_difference_deg']:.4f} deg (rms {fwd['rms_command_difference_deg']:.4f}) on the "
            f"±12 deg grid, largest at x' = {fwd['at_x_deg']:g}, y = {fwd['at_y_deg']:g}",
        ]
        params = _h_params("H1", H1, "H1 maps reference angles (X, Y) to stage angles (x', y), h33 = 1")
        residuals = dict(res_h1)
        fit_info: dict[str, Any] = {"n_points": int(sx.size), "n_points_h1": int(use.sum()), "points": points,
                                    "offaxis": offaxis, "h1": _stats(np.concatenate(list(res_h1.values())), 8),
                                    "levelling_residual_all_points": residual_summary(level_res, "deg", False),
                                    "offaxis_forward_vs_exact": fwd}
        cov = None
        cov_names: list[str] = []
        state: dict[str, Any] = {"has_meas": has_meas(data), "offaxis": offaxis}
        if has_meas(data):
            mx, my = columns(data, MEAS_COLUMNS)
            # Two sensors on one table: no stage coupling between them, so every point serves H2.
            H2 = fit_projective(mx, my, rx, ry, what="H2 (measurement -> reference)")
            h2 = H2.ravel()[:8]

            def r2(h):
                qx, qy = _apply_h(h, mx, my)
                return np.concatenate([qx - rx, qy - ry])

            r = r2(h2)
            st = _stats(r, 8)
            params.update(_h_params("H2", H2, "H2 maps measurement readings (a, b) to reference angles (X, Y)"))
            n = mx.size
            residuals.update({"ref_x_deg": r[:n], "ref_y_deg": r[n:]})
            fit_info["h2"] = st
            h2_note = (f"H2 (measurement -> reference) fitted by normalised DLT on all {n} points: both sensors ride "
                       "on the table, so the stage coupling does not enter between them; ")
            if st["sigma_deg"] is not None:
                cov = _numeric_cov(r2, h2, H_SCALES, st["sigma_deg"] ** 2)
                cov_names = [f"H2.{k}" for k in H_KEYS]
                state["meas_sigma_deg"] = st["sigma_deg"]
                notes.append(h2_note + "u_tilt from H2's covariance and the H2 residual as reading noise (which also "
                             "holds the reference's noise: conservative)")
            else:
                notes.append(h2_note + f"the {n} points determine its 8 parameters exactly and leave no residual to "
                             "estimate the noise: no covariance and no u_tilt")
        else:
            notes.append("no meas_x_deg/meas_y_deg columns: H2 not fitted, this model can level but not correct")
        return _model(self.name, _used_columns(data), params, notes, covariance_names=cov_names, covariance=cov,
                      residuals=residual_summary(residuals, "deg"), fit=fit_info, state=state,
                      options={"points": points, "offaxis": offaxis})

    def level(self, model: CalibrationModel, data: Columns) -> dict[str, np.ndarray]:
        tx, ty = _targets(data)
        xd, y = apply_projective(_h_of(model, "H1"), tx, ty)
        if model.state.get("offaxis", "exact") == "paper":
            x = offaxis_paper_forward_deg(xd, y)
        else:
            x = offaxis_exact_inverse_deg(xd, y)
        return stage_commands(model, x, y)

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, np.ndarray]:
        model_needs_meas(model)
        names = [f"H2.{k}" for k in H_KEYS]

        def f(p, inp):
            a, b = _apply_h(p, inp["meas_x_deg"], inp["meas_y_deg"])
            return np.column_stack([a, b])

        return _uncertain_correct(f, model.values(names), model.cov_of(names), data,
                                  float(model.state.get("meas_sigma_deg", 0.0)))


# --- coupling (seed 000 ref. [9]) ---------------------------------------------------------------
class CouplingMethod:
    """Ref. [9] as seed 000 describes it: the off-axis coupling model alone, no linear installation errors.

    Reading: the reference reads X = x - κ·error10(x, y), Y = y (κ = 1 is the bare geometry of eq. 9);
    calibration fits κ. The measurement sensor, by the same assumption, reads the table tilt directly
    (only an upside-down mounting, detected from the data, is undone): that is its H2-like step.
    """

    kind = "stage"
    name = "coupling"
    fit_required = FIT_REQUIRED
    fit_optional = FIT_OPTIONAL
    correct_required = MEAS_COLUMNS
    correct_optional = ()
    outputs = TILT_OUTPUTS

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel:
        sx, sy, rx, ry = columns(data, FIT_REQUIRED)
        require_spread(sx, sy, 3, "the coupling model")
        e = offaxis_error_deg(sx, sy)
        if float(e @ e) < 1e-12:
            raise DegenerateDataError("the coupling model needs points with both stages away from zero (off the "
                                      "θx = 0 and θy = 0 lines), where eq. (10)'s error is not zero")
        d = sx - rx
        kappa = float(e @ d / (e @ e))
        res = {"ref_x_deg": (sx - kappa * e) - rx, "ref_y_deg": sy - ry}
        r = np.concatenate(list(res.values()))
        st = _stats(r, 1)
        var_k = float(np.sum(res["ref_x_deg"] ** 2) / max(sx.size - 1, 1) / (e @ e))
        params = {"offaxis_coupling.kappa": Parameter(kappa, "1", note="x reading = x - kappa * eq.(10) error; "
                                                                        "1 is the bare stacked-stage geometry")}
        notes = ["ref. [9] as read from seed 000 §0 and §4.5: the nonlinear coupling between the two tilt axes "
                 "(the same as eq. 10) and nothing else; no zero offsets, yaws, scales or mounting tilts, so "
                 "those installation errors stay in the levelled and corrected values",
                 "levelling: y = Y, and x solves x - kappa * error10(x, y) = X (exact for kappa = 1: "
                 "x = asin(sin X / cos Y))"]
        state: dict[str, Any] = {"has_meas": has_meas(data)}
        if has_meas(data):
            sign, how = _meas_sign(data, options)
            state["meas_sign"] = sign.tolist()
            mx, my = columns(data, MEAS_COLUMNS)
            res.update({"meas_x_deg": sign[0] * mx - rx, "meas_y_deg": sign[1] * my - ry})
            state["meas_misfit_rms_deg"] = [float(np.sqrt(np.mean(res[c] ** 2))) for c in ("meas_x_deg", "meas_y_deg")]
            notes.append("this model cannot describe the measurement sensor: its H2-like step takes the measurement "
                         "reading as the table tilt (the model has no installation errors); the meas_* residuals "
                         "show what that leaves, and u_tilt is twice their RMS (the unmodelled installation error "
                         "taken as an uncertainty, not a GUM propagation)")
            if (mn := mirror_note(sign)) is not None:
                notes.append(f"{mn} ({how})")
        return _model(self.name, _used_columns(data), params, notes, covariance_names=["offaxis_coupling.kappa"],
                      covariance=np.array([[var_k]]), residuals=residual_summary(res, "deg"),
                      fit={"n_points": int(sx.size), **st}, state=state)

    def level(self, model: CalibrationModel, data: Columns) -> dict[str, np.ndarray]:
        tx, ty = _targets(data)
        k = model.value("offaxis_coupling.kappa")
        x0 = np.degrees(np.arcsin(np.clip(np.sin(np.radians(tx)) / np.cos(np.radians(ty)), -1.0, 1.0)))
        x, y = newton_2d(lambda u, v: (u - k * offaxis_error_deg(u, v), v), tx, ty, x0, ty.copy())
        return stage_commands(model, x, y)

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, np.ndarray]:
        model_needs_meas(model)
        sign = np.asarray(model.state.get("meas_sign", [1.0, 1.0]), dtype=float)
        mx, my = columns(data, MEAS_COLUMNS)
        ux, uy = model.state.get("meas_misfit_rms_deg", [0.0, 0.0])
        return {"tilt_x_deg": sign[0] * mx, "tilt_y_deg": sign[1] * my,
                "u_tilt_x_deg": np.full(mx.shape, 2.0 * ux), "u_tilt_y_deg": np.full(my.shape, 2.0 * uy)}


# --- axis-transform (seed 000 ref. [10]) -----------------------------------------------------------
def _axis_matrix(alpha_deg: float, beta_deg: float) -> np.ndarray:
    a, b = np.radians(alpha_deg), np.radians(beta_deg)
    return np.array([[np.cos(a), np.sin(a)], [-np.sin(b), np.cos(b)]])


def _axis_forward(p, u_deg, v_deg) -> tuple[np.ndarray, np.ndarray]:
    M = _axis_matrix(p[0], p[1])
    su, sv = np.sin(np.radians(u_deg)), np.sin(np.radians(v_deg))
    return (np.degrees(np.arcsin(np.clip(M[0, 0] * su + M[0, 1] * sv, -1, 1))),
            np.degrees(np.arcsin(np.clip(M[1, 0] * su + M[1, 1] * sv, -1, 1))))


def _axis_inverse(p, a_deg, b_deg) -> tuple[np.ndarray, np.ndarray]:
    Mi = np.linalg.inv(_axis_matrix(p[0], p[1]))
    sa, sb = np.sin(np.radians(a_deg)), np.sin(np.radians(b_deg))
    return (np.degrees(np.arcsin(np.clip(Mi[0, 0] * sa + Mi[0, 1] * sb, -1, 1))),
            np.degrees(np.arcsin(np.clip(Mi[1, 0] * sa + Mi[1, 1] * sb, -1, 1))))


def _fit_axis_pair(u, v, a, b, what: str) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], dict[str, Any]]:
    obs = np.concatenate([a, b])

    def resid(p):
        fa, fb = _axis_forward(p, u, v)
        return np.concatenate([fa, fb]) - obs

    sol = least_squares(resid, np.zeros(2), method="lm", xtol=1e-14, ftol=1e-14)
    if not sol.success or not np.all(np.isfinite(sol.x)):
        raise DegenerateDataError(f"{what}: the fit did not converge ({sol.message})")
    r = resid(sol.x)
    st = _stats(r, 2)
    cov = _numeric_cov(resid, sol.x, np.array([0.1, 0.1]), st["sigma_deg"] ** 2)
    n = u.size
    return sol.x, cov, {"x": r[:n], "y": r[n:]}, st


class AxisTransformMethod:
    """Ref. [10] as seed 000 describes it: both sensing axes non-parallel to the tilt axes, solved by a
    coordinate transform; no vertical-direction errors (no zero offsets or plane tilts) and no coupling.

    Reading: the stage angles are taken as the table's attitude (x about Y, y about X) and each sensing
    axis lies in the table plane at a small angle to its tilt axis, so it reads the projection of gravity:
    sin X = cos α sin x + sin α sin y, sin Y = -sin β sin x + cos β sin y. Calibration fits α, β; the
    measurement sensor gets the same transform against the reference (its H2-like step).
    """

    kind = "stage"
    name = "axis-transform"
    fit_required = FIT_REQUIRED
    fit_optional = FIT_OPTIONAL
    correct_required = MEAS_COLUMNS
    correct_optional = ()
    outputs = TILT_OUTPUTS

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel:
        sx, sy, rx, ry = columns(data, FIT_REQUIRED)
        require_spread(sx, sy, 3, "the axis-transform model")
        p, cov, r, st = _fit_axis_pair(sx, sy, rx, ry, "stage -> reference axis angles")
        names = ["stage_to_ref.x_axis_angle_deg", "stage_to_ref.y_axis_angle_deg"]
        params = {names[0]: Parameter(float(p[0]), "deg", note="angle of the reference x axis to the upper stage's "
                                                               "tilt direction, in the table plane"),
                  names[1]: Parameter(float(p[1]), "deg", note="angle of the reference y axis to the lower stage's "
                                                               "tilt direction, in the table plane")}
        res = {"ref_x_deg": r["x"], "ref_y_deg": r["y"]}
        notes = ["ref. [10] as read from seed 000 §0 and §4.5: a coordinate transform for two sensing axes each "
                 "non-parallel to its tilt axis, sin(reading) = projection of gravity on the axis; the stage "
                 "angles are taken as the attitude (no off-axis coupling) and there are no vertical-direction "
                 "errors (no zero offsets or plane tilts)",
                 "levelling: (sin x, sin y) = M(alpha, beta)^-1 (sin X, sin Y), exact for this model"]
        state: dict[str, Any] = {"has_meas": has_meas(data)}
        cov_all = cov
        cov_names = list(names)
        fit_info: dict[str, Any] = {"n_points": int(sx.size), "stage_to_ref": st}
        if has_meas(data):
            sign, how = _meas_sign(data, options)
            mx, my = columns(data, MEAS_COLUMNS)
            q, cq, rq, sq = _fit_axis_pair(rx, ry, sign[0] * mx, sign[1] * my, "measurement -> reference axis angles")
            mnames = ["meas_to_ref.x_axis_angle_deg", "meas_to_ref.y_axis_angle_deg"]
            params[mnames[0]] = Parameter(float(q[0]), "deg", note="angle of the measurement x axis to the reference x axis")
            params[mnames[1]] = Parameter(float(q[1]), "deg", note="angle of the measurement y axis to the reference y axis")
            cov_all = np.block([[cov, np.zeros((2, 2))], [np.zeros((2, 2)), cq]])
            cov_names += mnames
            res.update({"meas_x_deg": rq["x"], "meas_y_deg": rq["y"]})
            state["meas_sign"] = sign.tolist()
            state["meas_sigma_deg"] = sq["sigma_deg"]
            fit_info["meas_to_ref"] = sq
            notes.append("the measurement sensor is mapped through the same transform against the reference "
                         "(its H2-like step: axis angles only, no zero offsets)")
            if (mn := mirror_note(sign)) is not None:
                notes.append(f"{mn} ({how})")
        return _model(self.name, _used_columns(data), params, notes, covariance_names=cov_names, covariance=cov_all,
                      residuals=residual_summary(res, "deg"), fit=fit_info, state=state)

    def level(self, model: CalibrationModel, data: Columns) -> dict[str, np.ndarray]:
        tx, ty = _targets(data)
        p = model.values(["stage_to_ref.x_axis_angle_deg", "stage_to_ref.y_axis_angle_deg"])
        x, y = _axis_inverse(p, tx, ty)
        return stage_commands(model, x, y)

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, np.ndarray]:
        model_needs_meas(model)
        names = ["meas_to_ref.x_axis_angle_deg", "meas_to_ref.y_axis_angle_deg"]
        sign = np.asarray(model.state.get("meas_sign", [1.0, 1.0]), dtype=float)

        def f(p, inp):
            a, b = _axis_inverse(p, sign[0] * inp["meas_x_deg"], sign[1] * inp["meas_y_deg"])
            return np.column_stack([a, b])

        return _uncertain_correct(f, model.values(names), model.cov_of(names), data,
                                  float(model.state.get("meas_sigma_deg", 0.0)))


# --- kinematic (spec §2) ------------------------------------------------------------------------------
class KinematicMethod:
    """The chain of spec §2 fitted by nonlinear least squares; the measurement sensor's own mounting
    fitted against the reference. Parameters the points cannot separate are held and said so."""

    kind = "stage"
    name = "kinematic"
    fit_required = FIT_REQUIRED
    fit_optional = FIT_OPTIONAL
    correct_required = MEAS_COLUMNS
    correct_optional = ()
    outputs = TILT_OUTPUTS

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel:
        sx, sy, rx, ry = columns(data, FIT_REQUIRED)
        loss = check_loss(options.loss)
        require_spread(sx, sy, 5, "the kinematic model")
        bench = StageBench(**options.extra.get("bench", {}))
        pts = StagePoints.from_columns(data)
        chain = fit_chain(bench, pts, rx, ry, loss=loss, periodic=bool(options.extra.get("periodic_error", False)),
                          max_nfev=int(options.extra.get("max_nfev", 200)))
        params: dict[str, Parameter] = {}
        for k, v in zip(chain.keys, chain.values):
            params[param_label(k)] = Parameter(float(v), unit_of(k))
        for k, why in chain.fixed.items():
            params[param_label(k)] = Parameter(0.0, unit_of(k), fixed=True, note=why)
        cov_names = [param_label(k) for k in chain.keys]
        blocks = [chain.covariance]
        residuals = dict(chain.residuals)
        notes = [
            "chain (spec §2): desk · Rot(lower axis, y) · Rot(upper axis, x) · top · reference seat · reference yaw, "
            "with stage scale and backlash on the commands; fitted to ref_x_deg/ref_y_deg with "
            f"scipy.optimize.least_squares (loss {loss}); the reference is the lab's standard, so its own "
            "zero, scale and non-orthogonality are not fitted (its readings are the table tilt)",
            "gauge: a common rotation of desk, stage axes and table top changes no reading, so one parameter "
            "of each of (lower yaw, perpendicularity, ref yaw), (desk x, lower pitch, top x), (desk y, "
            "upper pitch, top y) and the reference seat (composes with the top) is held; the fitted "
            "perpendicularity and ref yaw are then relative to the lower axis, desk tilts include the "
            "stages' zero offsets",
        ]
        notes += [f"{param_label(k)}: {why}" for k, why in chain.fixed.items()]
        notes += [f"{a} and {b} are correlated {c:+.5f} (near-degenerate: they differ only by 1 - cos of the "
                  "other stage's angle; kept, since holding either leaves that difference as model error; their sum "
                  "is well determined)"
                  for a, b, c in chain.correlations]
        fit_info: dict[str, Any] = {
            "n_points": int(sx.size), "chain": {"dof": chain.dof, "sigma_deg": chain.sigma, "converged": chain.converged,
                                                "nfev": chain.nfev, "loss": loss,
                                                "scaled_jacobian_singular_values": chain.singular_values.tolist()},
        }
        state: dict[str, Any] = {"has_meas": has_meas(data), "bench": asdict(bench),
                                 "chain_parameters": [param_label(k) for k in list(chain.keys) + list(chain.fixed)],
                                 "approach": [1.0, 1.0]}
        if has_meas(data):
            sign, how = _meas_sign(data, options)
            mx, my = columns(data, MEAS_COLUMNS)
            meas = fit_meas(rx, ry, mx, my, sign, loss=loss)
            units = {p[0]: p[1] for p in MEAS_PARAMS}
            for name, v in zip(MEAS_NAMES, meas.values):
                fixed = name in meas.fixed
                params[name] = Parameter(float(v), units[name], fixed=fixed, note=meas.fixed.get(name, ""))
            cov_names += meas.names
            blocks.append(meas.covariance)
            residuals.update(meas.residuals)
            state.update({"meas_sign": sign.tolist(), "meas_sigma_deg": meas.sigma})
            fit_info["meas"] = {"dof": meas.dof, "sigma_deg": meas.sigma, "nfev": meas.nfev}
            notes.append("measurement sensor: zero offsets, scales, yaw, non-orthogonality and seat tilt, all relative "
                         "to the reference sensor's frame (the table-tilt frame), fitted to meas_* against ref_* "
                         "(no stage parameter enters, stage repeatability stays out); correct inverts it in "
                         "closed form; u_tilt from its covariance and the fit's residual as reading noise "
                         "(which also holds the reference's noise: conservative)")
            notes += [f"{n}: {why}" for n, why in meas.fixed.items()]
            notes += [f"{a} and {b} are correlated {c:+.5f} (near-degenerate: they differ only by 1 - cos of the "
                      "tilt; kept, their sum is well determined)"
                      for a, b, c in meas.correlations]
            if (mn := mirror_note(sign)) is not None:
                notes.append(f"{mn} ({how})")
        else:
            notes.append("no meas_x_deg/meas_y_deg columns: this model can level but not correct")
        notes.append("the covariance is block-diagonal between the chain and the measurement sensor (separate fits)")
        k = sum(b.shape[0] for b in blocks)
        cov = np.zeros((k, k))
        i = 0
        for b in blocks:
            cov[i:i + b.shape[0], i:i + b.shape[0]] = b
            i += b.shape[0]
        return _model(self.name, _used_columns(data), params, notes, covariance_names=cov_names, covariance=cov,
                      residuals=residual_summary(residuals, "deg"), fit=fit_info, state=state, options={"loss": loss})

    @staticmethod
    def chain_model(model: CalibrationModel) -> ChainModel:
        bench = StageBench(**model.state.get("bench", {}))
        values = {}
        for name in model.state.get("chain_parameters", []):
            e, p = name.split(".", 1)
            values[(e, p)] = model.value(name)
        return ChainModel.from_values(bench, values)

    def level(self, model: CalibrationModel, data: Columns) -> dict[str, np.ndarray]:
        tx, ty = _targets(data)
        ap = model.state.get("approach", [1.0, 1.0])
        dx = np.asarray(data.get("dir_x", ap[0]), dtype=float)
        dy = np.asarray(data.get("dir_y", ap[1]), dtype=float)
        chain = self.chain_model(model)
        x, y = chain.level(tx, ty, dx, dy)
        return stage_commands(model, x, y)

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, np.ndarray]:
        model_needs_meas(model)
        sign = np.asarray(model.state.get("meas_sign", [1.0, 1.0]), dtype=float)
        mx, my = columns(data, MEAS_COLUMNS)
        X, Y, ux, uy = meas_inverse_with_u(model.values(MEAS_NAMES), model.cov_of(list(MEAS_NAMES)), sign, mx, my,
                                           float(model.state.get("meas_sigma_deg", 0.0)))
        return {"tilt_x_deg": X, "tilt_y_deg": Y, "u_tilt_x_deg": expanded(ux), "u_tilt_y_deg": expanded(uy)}


HOMOGRAPHY = register(HomographyMethod())
COUPLING = register(CouplingMethod())
AXIS_TRANSFORM = register(AxisTransformMethod())
KINEMATIC = register(KinematicMethod())
__all__ = ["HOMOGRAPHY", "COUPLING", "AXIS_TRANSFORM", "KINEMATIC", "LEVEL_OUTPUTS"]
