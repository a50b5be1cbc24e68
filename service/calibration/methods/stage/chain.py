"""The kinematic chain of docs/models.md §2 as a calibration: which parameters the data can separate,
the fit itself (service.calibration.stage_effect_fit), and the chain run forwards and backwards.

Identifiability. Only the up vector in the reference frame is observable, so the chain
desk · Rot(lower axis, θy) · Rot(upper axis, θx) · top · ref seat · ref yaw has an exact 3-D
gauge: a common rotation of desk, both axes and table top changes no reading. Its three
directions are (lower yaw, perpendicularity, ref yaw) about the vertical, (desk x, lower
pitch, top x) about Y and (desk y, upper pitch, top y) about X; and the ref seat composes with
the table top. Candidates are therefore taken in a fixed order of physical preference and
each one is kept only if its (scaled) Jacobian column is not, to within 1e-3, a combination
of the columns already kept; the others are held at zero and the model notes say what they
were merged into. The Jacobian is taken on the data's own points, so a grid that does not
exercise an effect (e.g. backlash when every point is approached from one side) fixes it
too. Near-degenerate pairs that survive (desk vs top: they differ by 1 - cos θ of the other
stage, 2 % at 12°) are kept, because dropping them leaves a model error of the order of the
noise, and their correlation is reported.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from service.calibration.differences import central_jacobian
from service.calibration.methods.stage.common import (
    MEAS_PARAMS,
    meas_forward,
    newton_2d,
)
from service.calibration.stage_effect_fit import StageEffectModel, StagePoints, fit_stage_effects, param_label, robust_scale, typical_scale
from service.errors import DegenerateDataError, FitError, InputError
from service.io.columns import REF
from service.physics.effects import STAGE_EFFECTS, EffectSet
from service.physics.stage import StageBench, StageGeometry, offaxis_inverse_deg

ParamKey = tuple[str, str]
IDENTIFIABLE_REL = 1e-3  # a column closer than this (relative) to the span of the kept ones is not separable

# Order of physical preference: the first of a degenerate group is kept.
CHAIN_CANDIDATES: tuple[ParamKey, ...] = (
    ("stage_scale", "x"),
    ("stage_scale", "y"),
    ("mounting_tilt", "desk_x_deg"),
    ("mounting_tilt", "desk_y_deg"),
    ("sensor_yaw", "ref_deg"),
    ("axis_misalignment", "perpendicularity_deg"),
    ("mounting_tilt", "top_x_deg"),
    ("mounting_tilt", "top_y_deg"),
    ("backlash", "x_deg"),
    ("backlash", "y_deg"),
    ("axis_misalignment", "lower_yaw_deg"),
    ("axis_misalignment", "lower_pitch_deg"),
    ("axis_misalignment", "upper_pitch_deg"),
    ("mounting_tilt", "ref_x_deg"),
    ("mounting_tilt", "ref_y_deg"),
)
PERIODIC: tuple[ParamKey, ...] = (("periodic_error", "x_amp_deg"), ("periodic_error", "x_phase_deg"),
                                  ("periodic_error", "y_amp_deg"), ("periodic_error", "y_phase_deg"))
# Effects a record may add to the chain (a diagnosis names them): their registry parameters become free, with
# the start values the fit needs (a periodic error's phase is undefined at zero amplitude). The reference sensor's
# own terms, because the chain is fitted to its readings; backlash and the coupling are in the chain already.
EXTRA_EFFECTS: dict[str, tuple[tuple[ParamKey, float], ...]] = {
    "periodic_error": tuple(zip(PERIODIC, (0.002, 0.0, 0.002, 0.0))),
    "sensor_nonlinearity": ((("sensor_nonlinearity", "ref_x_per_deg"), 0.0),
                            (("sensor_nonlinearity", "ref_y_per_deg"), 0.0)),
}
IN_CHAIN = ("backlash", "offaxis_coupling")
ESSENTIAL = (("stage_scale", "x"), ("stage_scale", "y"), ("mounting_tilt", "desk_x_deg"),
             ("mounting_tilt", "desk_y_deg"))
REF_OBS = REF


def unit_of(key: ParamKey) -> str:
    return STAGE_EFFECTS[key[0]].param(key[1]).unit


# --- identifiability -------------------------------------------------------------------------
@dataclass
class Selection:
    kept: list[int]
    fixed: list[int]
    merged_into: dict[int, list[tuple[int, float]]]  # fixed index -> [(kept index, coefficient)]
    rel_residual: list[float]


def select_identifiable(J: NDArray[np.float64], scales: NDArray[np.float64], rel_tol: float = IDENTIFIABLE_REL) -> Selection:
    """Greedy column selection in candidate order: keep a column if it adds a new direction."""
    Js = J * scales
    kept: list[int] = []
    fixed: list[int] = []
    merged: dict[int, list[tuple[int, float]]] = {}
    rels = []
    for i in range(Js.shape[1]):
        col = Js[:, i]
        norm = float(np.linalg.norm(col))
        if norm == 0.0:
            rels.append(0.0)
            fixed.append(i)
            merged[i] = []
            continue
        if kept:
            A = Js[:, kept]
            coef = np.linalg.lstsq(A, col, rcond=None)[0]
            rel = float(np.linalg.norm(col - A @ coef)) / norm
        else:
            coef, rel = np.zeros(0), 1.0
        rels.append(rel)
        if rel > rel_tol:
            kept.append(i)
        else:
            fixed.append(i)
            # physical coefficients: a change d of parameter i looks like changes coef_j * s_i / s_j of kept j
            merged[i] = [(kept[j], float(coef[j] * scales[i] / scales[kept[j]])) for j in range(len(kept))
                         if abs(coef[j]) > 0.05 * np.max(np.abs(coef))]
    return Selection(kept, fixed, merged, rels)


def numeric_jacobian(fun: Callable[[NDArray[np.float64]], NDArray[np.float64]], x0: NDArray[np.float64],
                     scales: NDArray[np.float64]) -> NDArray[np.float64]:
    """The chain's Jacobian for identifiability and covariance: the one finite-difference rule, stepping
    a thousandth of each parameter's typical magnitude (the linearisation the selection judges)."""
    return central_jacobian(fun, x0, 1e3 * np.asarray(scales))


# --- the chain fit -----------------------------------------------------------------------------
@dataclass
class ChainFit:
    keys: list[ParamKey]  # free, in fit order
    values: NDArray[np.float64]
    covariance: NDArray[np.float64]
    fixed: dict[ParamKey, str]  # held at zero -> why
    residuals: dict[str, NDArray[np.float64]]
    sigma: float
    dof: int
    converged: bool
    nfev: int
    singular_values: NDArray[np.float64]
    correlations: list[tuple[str, str, float]]


def fit_chain(bench: StageBench, pts: StagePoints, ref_x: NDArray[np.float64], ref_y: NDArray[np.float64], loss: str = "linear",
              periodic: bool = False, max_nfev: int = 200, effects: Sequence[str] = ()) -> ChainFit:
    """Least-squares fit of the identifiable chain parameters to the reference readings, with the parameters of
    the extra `effects` (EXTRA_EFFECTS) free as well."""
    unknown = [e for e in effects if e not in EXTRA_EFFECTS and e not in IN_CHAIN]
    if unknown:
        raise InputError(f"effects: {', '.join(unknown)} cannot be added to the kinematic chain; it takes "
                         f"{', '.join(EXTRA_EFFECTS)} (and has {', '.join(IN_CHAIN)} already)")
    candidates = list(CHAIN_CANDIDATES)
    all_model = StageEffectModel(bench, {}, candidates)
    scales = np.array([typical_scale(k) for k in candidates])

    def pred(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return all_model.predict(x, pts, REF_OBS).ravel()

    J = numeric_jacobian(pred, np.zeros(len(candidates)), scales)
    sel = select_identifiable(J, scales)
    missing = [candidates[i] for i in sel.fixed if candidates[i] in ESSENTIAL]
    if missing:
        what = ", ".join(param_label(k) for k in missing)
        raise DegenerateDataError(f"the stage points do not determine {what}: the data need both stages moved to "
                                  "several angles each, with points off both axes (e.g. a 3 x 3 grid or larger)")
    free = [candidates[i] for i in sel.kept]
    fixed: dict[ParamKey, str] = {}
    for i in sel.fixed:
        into = sel.merged_into[i]
        if into:
            parts = ", ".join(f"{param_label(candidates[j])} ({c:+.2g} per unit)" for j, c in into)
            why = f"not separable on these points from {parts} (relative residual {sel.rel_residual[i]:.1e}); held at 0"
        else:
            why = "these points do not exercise it; held at 0"
        fixed[candidates[i]] = why
    x0 = np.zeros(len(free))
    extra = ["periodic_error"] if periodic else []
    extra += [e for e in effects if e in EXTRA_EFFECTS and e not in extra]
    for e in extra:
        free += [k for k, _ in EXTRA_EFFECTS[e]]
        x0 = np.concatenate([x0, [v for _, v in EXTRA_EFFECTS[e]]])
    model = StageEffectModel(bench, {}, free)
    observed = {"ref_x_deg": ref_x, "ref_y_deg": ref_y}
    try:
        fit = fit_stage_effects(model, pts, observed, x0=x0, loss=loss, max_nfev=max_nfev)  # robust scale: see fit_stage_effects
    except FitError as exc:
        raise DegenerateDataError(f"the kinematic fit failed on these points: {exc}") from None
    if not fit.converged:
        raise DegenerateDataError(f"the kinematic fit did not converge in {fit.nfev} evaluations ({fit.message}); "
                                  "the points do not pin the bench down: add points over both stages' ranges")
    if not np.all(np.isfinite(fit.covariance)):
        raise DegenerateDataError("the kinematic fit has no finite covariance: the points do not separate its parameters")
    sd = np.sqrt(np.clip(np.diag(fit.covariance), 1e-300, None))
    corr = fit.covariance / np.outer(sd, sd)
    pairs = []
    for i in range(len(free)):
        for j in range(i + 1, len(free)):
            if abs(corr[i, j]) > 0.95:
                pairs.append((param_label(free[i]), param_label(free[j]), float(corr[i, j])))
    return ChainFit(free, fit.values, fit.covariance, fixed, fit.residuals, fit.sigma, fit.dof, fit.converged,
                    fit.nfev, fit.jac_singular_values, pairs)


# --- the chain run forwards and backwards (unquantised commands) ------------------------------------
def actual_angles_deg(fx: EffectSet, bench: StageBench, cmd_x: ArrayLike, cmd_y: ArrayLike, dir_x: ArrayLike = 0.0,
                      dir_y: ArrayLike = 0.0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Stage angles reached for commands (no pulse rounding, no noise): the model's mean bench."""
    out = []
    for ax, cmd, d, period in (("x", cmd_x, dir_x, bench.worm_period_x_deg), ("y", cmd_y, dir_y, bench.worm_period_y_deg)):
        cmd_deg = np.asarray(cmd, dtype=float)
        ang = cmd_deg * (1.0 + fx.get("stage_scale", ax)) - np.asarray(d, dtype=float) * fx.get("backlash", f"{ax}_deg") / 2.0
        amp = fx.get("periodic_error", f"{ax}_amp_deg")
        if amp:
            ang = ang + amp * np.sin(2 * np.pi * cmd_deg / period + np.radians(fx.get("periodic_error", f"{ax}_phase_deg")))
        out.append(ang)
    return out[0], out[1]


class ChainModel:
    """A bench (fitted or true) that can predict table tilt from commands and invert that."""

    def __init__(self, bench: StageBench, fx: EffectSet):
        self.bench = bench
        self.fx = fx
        self.geometry = StageGeometry.from_effects(bench, fx)

    @classmethod
    def from_values(cls, bench: StageBench, values: Mapping[ParamKey, float]) -> ChainModel:
        eff: dict[str, dict[str, float]] = {}
        for (e, p), v in values.items():
            if e == "noise":
                continue
            eff.setdefault(e, {})[p] = float(v)
        return cls(bench, EffectSet.from_mapping("stage", eff))

    def tilt(self, cmd_x: ArrayLike, cmd_y: ArrayLike, dir_x: ArrayLike = 0.0, dir_y: ArrayLike = 0.0) -> tuple[NDArray[np.float64],
                                                                                                                NDArray[np.float64]]:
        ax, ay = actual_angles_deg(self.fx, self.bench, cmd_x, cmd_y, dir_x, dir_y)
        r = self.geometry.readings_deg(np.radians(np.atleast_1d(ax)), np.radians(np.atleast_1d(ay)))
        return r["tilt_x"], r["tilt_y"]

    def level(self, target_x: ArrayLike, target_y: ArrayLike, dir_x: ArrayLike = 1.0, dir_y: ArrayLike = 1.0) -> tuple[NDArray[np.float64],
                                                                                                                       NDArray[np.float64]]:
        """Commands that bring the table to the wanted tilt: 2-D Newton from the ideal inverse."""
        tx = np.atleast_1d(np.asarray(target_x, dtype=float))
        ty = np.atleast_1d(np.asarray(target_y, dtype=float))
        y0 = ty.copy()
        x0 = offaxis_inverse_deg(tx, ty, clip=True)
        return newton_2d(lambda u, v: self.tilt(u, v, dir_x, dir_y), tx, ty, x0, y0)


# --- the measurement sensor fit --------------------------------------------------------------------
@dataclass
class MeasFit:
    names: list[str]  # free
    values: NDArray[np.float64]  # all MEAS_PARAMS, fixed ones at 0
    covariance: NDArray[np.float64]  # over `names`
    fixed: dict[str, str]
    residuals: dict[str, NDArray[np.float64]]
    sigma: float
    dof: int
    converged: bool
    nfev: int
    correlations: list[tuple[str, str, float]]


def fit_meas(ref_x: NDArray[np.float64], ref_y: NDArray[np.float64], meas_x: NDArray[np.float64], meas_y: NDArray[np.float64],
             sign: NDArray[np.float64], loss: str = "linear", max_nfev: int = 200) -> MeasFit:
    """Mounting of the measurement sensor in the reference frame, from its readings against the reference's.

    The two sensors ride on one rigid table, so no stage parameter enters: meas = f(ref) exactly
    up to noise. Regressing on the reference (not on the stage commands) keeps stage
    repeatability out of the fit.
    """
    all_names = [p[0] for p in MEAS_PARAMS]
    scales = np.array([p[2] for p in MEAS_PARAMS])
    obs: NDArray[np.float64] = np.concatenate([meas_x, meas_y])

    def pred_all(p: NDArray[np.float64]) -> NDArray[np.float64]:
        a, b = meas_forward(p, sign, ref_x, ref_y)
        return np.concatenate([a, b])

    J = numeric_jacobian(pred_all, np.zeros(len(all_names)), scales)
    sel = select_identifiable(J, scales)
    kept = sel.kept
    fixed = {}
    for i in sel.fixed:
        into = ", ".join(f"{all_names[j]} ({c:+.2g} per unit)" for j, c in sel.merged_into[i])
        fixed[all_names[i]] = (f"not separable on these points from {into or 'the others'} "
                               f"(relative residual {sel.rel_residual[i]:.1e}); held at 0")
    if len(obs) <= len(kept):
        raise DegenerateDataError(f"{len(meas_x)} points are too few for the {len(kept)} parameters of the "
                                  "measurement sensor's mounting")

    def full(q: NDArray[np.float64]) -> NDArray[np.float64]:
        p = np.zeros(len(all_names))
        p[kept] = q
        return p

    def resid(q: NDArray[np.float64]) -> NDArray[np.float64]:
        return pred_all(full(q)) - obs

    q0 = np.zeros(len(kept))
    kw = {}
    if loss != "linear":
        pre = least_squares(resid, q0, x_scale=scales[kept], method="trf", max_nfev=max_nfev)
        kw["f_scale"] = robust_scale(pre.fun)
        q0 = pre.x
    sol = least_squares(resid, q0, x_scale=scales[kept], loss=loss, method="trf",
                        max_nfev=max_nfev, xtol=1e-12, ftol=1e-12, gtol=1e-12, **kw)
    if not sol.status > 0 or not np.all(np.isfinite(sol.x)):
        raise DegenerateDataError(f"the measurement-sensor fit did not converge ({sol.message}); "
                                  "the points do not determine its mounting")
    r = resid(sol.x)
    dof = max(r.size - len(kept), 1)
    s2 = float(r @ r) / dof
    Jk = numeric_jacobian(lambda q: pred_all(full(q)), sol.x, scales[kept])
    sv = np.linalg.svd(Jk * scales[kept], compute_uv=False)
    if sv[-1] <= 1e-8 * sv[0]:
        raise DegenerateDataError("the points do not separate the measurement sensor's mounting parameters")
    cov = np.linalg.inv(Jk.T @ Jk).astype(np.float64, copy=False) * s2
    sd = np.sqrt(np.diag(cov))
    corr = cov / np.outer(sd, sd)
    names = [all_names[i] for i in kept]
    pairs = [(names[i], names[j], float(corr[i, j])) for i in range(len(kept)) for j in range(i + 1, len(kept))
             if abs(corr[i, j]) > 0.95]
    n = len(meas_x)
    return MeasFit(names, full(sol.x), cov, fixed, {"meas_x_deg": r[:n], "meas_y_deg": r[n:]}, float(np.sqrt(s2)),
                   dof, True, int(sol.nfev), pairs)
