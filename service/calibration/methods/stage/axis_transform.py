"""Seed 000 ref. [10] as seed 000 describes it: sensing axes non-parallel to the tilt axes, a
coordinate transform and nothing else."""

from __future__ import annotations

from collections.abc import Mapping
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from service.calibration.methods.stage.base import (
    FIT_REQUIRED,
    MIN_THREE_WAY_POINTS,
    Columns,
    StageMethod,
    ThreeWay,
    bench_state,
    fit_stats,
    meas_dof,
    meas_reading_noise,
    meas_sign,
    noise_state,
    numeric_cov,
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
    has_meas,
    mirror_note,
    model_needs_meas,
    require_spread,
)
from service.calibration.model import (
    CalibrationModel,
    FitInfo,
    FitStats,
    ModelState,
    Parameter,
    residual_summary,
)
from service.calibration.projective import apply_projective, fit_projective
from service.calibration.registry import FitOptions
from service.calibration.uncertainty import expanded_with_bias
from service.errors import DegenerateDataError
from service.io.columns import K_OUTPUTS
from service.physics.stage import offaxis_reading_deg


def _axis_matrix(alpha_deg: float, beta_deg: float) -> NDArray[np.float64]:
    alpha, beta = np.radians(alpha_deg), np.radians(beta_deg)
    return np.array([[np.cos(alpha), np.sin(alpha)], [-np.sin(beta), np.cos(beta)]])


def _axis_forward(
    p: NDArray[np.float64], u_deg: ArrayLike, v_deg: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    matrix = _axis_matrix(p[0], p[1])
    su, sv = np.sin(np.radians(u_deg)), np.sin(np.radians(v_deg))
    return (
        np.degrees(np.arcsin(np.clip(matrix[0, 0] * su + matrix[0, 1] * sv, -1, 1))),
        np.degrees(np.arcsin(np.clip(matrix[1, 0] * su + matrix[1, 1] * sv, -1, 1))),
    )


def _axis_inverse(
    p: NDArray[np.float64], a_deg: ArrayLike, b_deg: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    Mi = np.linalg.inv(_axis_matrix(p[0], p[1]))
    sa, sb = np.sin(np.radians(a_deg)), np.sin(np.radians(b_deg))
    return (
        np.degrees(np.arcsin(np.clip(Mi[0, 0] * sa + Mi[0, 1] * sb, -1, 1))),
        np.degrees(np.arcsin(np.clip(Mi[1, 0] * sa + Mi[1, 1] * sb, -1, 1))),
    )


def _pair_residuals(
    p: NDArray[np.float64],
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    a: NDArray[np.float64],
    b: NDArray[np.float64],
) -> NDArray[np.float64]:
    """The transform of (u, v) less the readings (a, b), x rows then y rows."""
    fa, fb = _axis_forward(p, u, v)
    residuals: NDArray[np.float64] = np.concatenate([fa - a, fb - b])
    return residuals


def _fit_axis_pair(
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    a: NDArray[np.float64],
    b: NDArray[np.float64],
    what: str,
) -> tuple[NDArray[np.float64], NDArray[np.float64], dict[str, NDArray[np.float64]], FitStats]:
    def resid(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return _pair_residuals(p, u, v, a, b)

    sol = least_squares(resid, np.zeros(2), method="lm", xtol=1e-14, ftol=1e-14)
    if not sol.success or not np.all(np.isfinite(sol.x)):
        raise DegenerateDataError(f"{what}: the fit did not converge ({sol.message})")
    residuals = resid(sol.x)
    st = fit_stats(residuals, 2)
    # no sigma only without degrees of freedom (one point), where this fails as it always has
    cov = numeric_cov(resid, sol.x, np.array([0.1, 0.1]), cast(float, st["sigma_deg"]) ** 2)
    n = u.size
    return sol.x, cov, {"x": residuals[:n], "y": residuals[n:]}, st


def _uncorrected_bias(
    angles: NDArray[np.float64],
    ref_x: NDArray[np.float64],
    ref_y: NDArray[np.float64],
    meas_x: NDArray[np.float64],
    meas_y: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], FitStats, NDArray[np.float64]]:
    """The corrected calibration readings' mean offset from the reference per axis (what a model
    without zero offsets leaves), the axis angles' covariance from the scatter about that offset,
    the scatter's statistics (two angles and two means fitted) and the scatter itself (2 x n: x
    row, y row).

    The offset is the same at every point of the range, so it is no noise: counted as one, it
    would inflate every uncertainty until the interval held every point."""
    tilt_x, tilt_y = _axis_inverse(angles, meas_x, meas_y)
    diff = np.array([tilt_x - ref_x, tilt_y - ref_y])
    bias = diff.mean(axis=1)
    centred = diff - bias[:, None]
    scatter = fit_stats(centred.ravel(), 4)
    if scatter["sigma_deg"] is None:
        raise DegenerateDataError(
            "measurement -> reference axis angles: the points leave no degrees of freedom"
        )
    cov = numeric_cov(
        lambda p: _pair_residuals(p, ref_x, ref_y, meas_x, meas_y),
        angles,
        np.array([0.1, 0.1]),
        scatter["sigma_deg"] ** 2,
    )
    return bias, cov, scatter, centred


def _axis_scatter_variances(centred: NDArray[np.float64]) -> list[float]:
    """Each axis's variance about its bias, on n - 2 degrees of freedom (its mean and its angle)."""
    dof = max(centred.shape[1] - 2, 1)
    return [float(row @ row / dof) for row in centred]


def _three_way(
    stage_x: NDArray[np.float64],
    stage_y: NDArray[np.float64],
    ref_x: NDArray[np.float64],
    ref_y: NDArray[np.float64],
    centred: NDArray[np.float64],
) -> ThreeWay | None:
    """The three instruments at every point, for the reference's noise alone: the corrected
    measurement less the reference about its bias (`centred`), and the reference less a stage
    prediction.

    This model's own stage prediction misses by tenths of a degree (no zero offsets, no coupling),
    far too much to tell a thousandth's noise from; a projective map of the reference onto the
    decoupled stage angles (the homography's H1 on every point, fitted here for nothing else) leaves
    thousandths. None where that map cannot be fitted."""
    if stage_x.size < MIN_THREE_WAY_POINTS:  # too few to tell (meas_reading_noise says so)
        return None
    decoupled_x = offaxis_reading_deg(stage_x, stage_y)
    try:
        stage_map = fit_projective(ref_x, ref_y, decoupled_x, stage_y, what="stage prediction")
    except DegenerateDataError:
        return None
    predicted_x, predicted_y = apply_projective(stage_map, ref_x, ref_y)
    return ThreeWay(centred, np.array([predicted_x - decoupled_x, predicted_y - stage_y]))


class AxisTransformMethod(StageMethod):
    """Ref. [10] as seed 000 describes it: both sensing axes non-parallel to the tilt axes, solved
    by a coordinate transform; no vertical-direction errors (no zero offsets or plane tilts) and no
    coupling.

    Reading: the stage angles are taken as the table's attitude (x about Y, y about X) and each
    sensing axis lies in the table plane at a small angle to its tilt axis, so it reads the
    projection of gravity: sin X = cos α sin x + sin α sin y, sin Y = -sin β sin x + cos β sin y.
    Calibration fits α, β; the measurement sensor gets the same transform against the reference (its
    H2-like step).
    """

    name = "axis-transform"

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel:
        sx, sy, rx, ry = columns(data, FIT_REQUIRED)
        require_spread(sx, sy, 3, "the axis-transform model")
        angles, cov, stage_res, st = _fit_axis_pair(
            sx, sy, rx, ry, "stage -> reference axis angles"
        )
        names = ["stage_to_ref.x_axis_angle_deg", "stage_to_ref.y_axis_angle_deg"]
        params = {
            names[0]: Parameter(
                float(angles[0]),
                "deg",
                note="angle of the reference x axis to the upper stage's "
                "tilt direction, in the table plane",
            ),
            names[1]: Parameter(
                float(angles[1]),
                "deg",
                note="angle of the reference y axis to the lower stage's "
                "tilt direction, in the table plane",
            ),
        }
        res = {"ref_x_deg": stage_res["x"], "ref_y_deg": stage_res["y"]}
        notes = [
            (
                "ref. [10] as read from seed 000 §0 and §4.5: a coordinate transform for two "
                "sensing axes each non-parallel to its tilt axis, sin(reading) = projection of "
                "gravity on the axis; the stage angles are taken as the attitude (no off-axis "
                "coupling) and there are no vertical-direction errors (no zero offsets or plane "
                "tilts)"
            ),
            "levelling: (sin x, sin y) = M(alpha, beta)^-1 (sin X, sin Y), exact for this model",
        ]
        state: ModelState = {
            "has_meas": has_meas(data),
            **bench_state(*stage_hardware(options)[:2]),
        }
        cov_all = cov
        cov_names = list(names)
        fit_info: FitInfo = {"n_points": int(sx.size), "stage_to_ref": st}
        if has_meas(data):
            sign, how = meas_sign(data, options)
            mx, my = columns(data, MEAS_COLUMNS)
            meas_angles, _, rq, sq = _fit_axis_pair(
                rx, ry, sign[0] * mx, sign[1] * my, "measurement -> reference axis angles"
            )
            bias, cq, scatter, centred = _uncorrected_bias(
                meas_angles, rx, ry, sign[0] * mx, sign[1] * my
            )
            mnames = ["meas_to_ref.x_axis_angle_deg", "meas_to_ref.y_axis_angle_deg"]
            params[mnames[0]] = Parameter(
                float(meas_angles[0]),
                "deg",
                note="angle of the measurement x axis to the reference x axis",
            )
            params[mnames[1]] = Parameter(
                float(meas_angles[1]),
                "deg",
                note="angle of the measurement y axis to the reference y axis",
            )
            cov_all = np.block([[cov, np.zeros((2, 2))], [np.zeros((2, 2)), cq]])
            cov_names += mnames
            res.update({"meas_x_deg": rq["x"], "meas_y_deg": rq["y"]})
            state["meas_sign"] = sign.tolist()
            state["meas_sigma_deg"] = sq["sigma_deg"]
            state["meas_dof"] = scatter["dof"]
            state["meas_uncorrected_bias_deg"] = bias.tolist()
            # _uncorrected_bias has a sigma whenever it returns (it needs one for the covariance)
            assert scatter["sigma_deg"] is not None
            noise = meas_reading_noise(
                data,
                options,
                scatter["sigma_deg"],
                scatter["dof"],
                sign,
                _three_way(sx, sy, rx, ry, centred),
            )
            state.update(noise_state(noise))
            # each axis's own scatter about its bias: the misfit left along the range differs by
            # axis (the model's shape error is in x), and a pooled figure would blur the two
            ref_var = (noise.ref_sigma_deg or 0.0) ** 2
            state["meas_axis_reading_standard_uncertainty_deg"] = [
                float(np.sqrt(max(axis_s2 - ref_var, 0.0)))
                for axis_s2 in _axis_scatter_variances(centred)
            ]
            notes.append(
                "uncorrected bias of the corrected tilt (the mean of corrected - reference over "
                "the points, which axis angles alone cannot absorb: no zero offsets) x "
                f"{bias[0]:+.4f} deg, y {bias[1]:+.4f} deg; U is the 95 % interval about zero of "
                "an error with that bias and the random part (not k x the rms, which would cover "
                "every point)"
            )
            notes.append(
                f"reading noise of one measurement reading {noise.sigma_deg:.3g} deg: "
                f"{noise.source}"
            )
            fit_info["meas_to_ref"] = sq
            notes.append(
                "the measurement sensor is mapped through the same transform against the reference "
                "(its H2-like step: axis angles only, no zero offsets)"
            )
            if (mn := mirror_note(sign)) is not None:
                notes.append(f"{mn} ({how})")
        return stage_model(
            self.name,
            used_columns(data),
            params,
            notes,
            covariance_names=cov_names,
            covariance=cov_all,
            residuals=residual_summary(res, "deg"),
            fit=fit_info,
            state=state,
        )

    def commands(
        self, model: CalibrationModel, data: Columns
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        tx, ty = targets(data)
        angles = model.values(["stage_to_ref.x_axis_angle_deg", "stage_to_ref.y_axis_angle_deg"])
        x, y = _axis_inverse(angles, tx, ty)
        return x, y

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, NDArray[np.float64]]:
        model_needs_meas(model)
        names = ["meas_to_ref.x_axis_angle_deg", "meas_to_ref.y_axis_angle_deg"]
        sign = np.asarray(model.state.get("meas_sign", [1.0, 1.0]), dtype=float)

        def f(
            p: NDArray[np.float64], inp: Mapping[str, NDArray[np.float64]]
        ) -> NDArray[np.float64]:
            tilt_x, tilt_y = _axis_inverse(
                p, sign[0] * inp["meas_x_deg"], sign[1] * inp["meas_y_deg"]
            )
            return np.column_stack([tilt_x, tilt_y])

        sigma, noise_dof = reading_noise_of(model)
        p, cov = model.values(names), model.cov_of(names)
        out = uncertain_correct(f, p, cov, data, sigma, meas_dof(model), noise_dof)
        bias = model.state.get("meas_uncorrected_bias_deg")
        per_axis = model.state.get("meas_axis_reading_standard_uncertainty_deg")
        if bias is not None and "u_tilt_x_deg" in out:
            for i, (axis, b, k_key) in enumerate(zip("xy", bias, K_OUTPUTS, strict=True)):
                own = (
                    out
                    if per_axis is None
                    else uncertain_correct(f, p, cov, data, per_axis[i], meas_dof(model), noise_dof)
                )
                expanded, k = own[f"u_tilt_{axis}_deg"], own[k_key]
                out[f"u_tilt_{axis}_deg"], out[k_key] = expanded_with_bias(b, expanded / k, k)
        return out


AXIS_TRANSFORM = AxisTransformMethod()
