"""The kinematic chain of docs/models.md §2 as a calibration: which parameters the data can
separate, the fit itself (service.calibration.stage_effect_fit), and the chain run forwards and
backwards.

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
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import OptimizeResult, least_squares

from service.calibration.differences import central_jacobian
from service.calibration.methods.stage.common import (
    MEAS_PARAMS,
    meas_forward,
    newton_2d,
)
from service.calibration.stage_effect_fit import (
    StageEffectFit,
    StageEffectModel,
    StagePoints,
    fit_stage_effects,
    param_label,
    param_unit,
    registry_effects,
    robust_scale,
    typical_scale,
)
from service.errors import DegenerateDataError, FitError, InputError
from service.io.columns import REF
from service.physics.effects import EffectSet
from service.physics.stage import StageBench, StageGeometry, offaxis_inverse_deg

ParamKey = tuple[str, str]
# a column closer than this (relative) to the span of the kept ones is not separable
IDENTIFIABLE_REL = 1e-3
# a column smaller than this (relative to the largest) is not exercised by the points
UNEXERCISED_REL = 1e-9

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
# Effects a record may add to the chain (a diagnosis names them), by the parameters each adds,
# parametrised so the fit is linear in them from its start at zero: a worm's periodic error as a
# sine/cosine pair per stage (amplitude and phase are singular at zero amplitude), the reference
# sensor's own terms because the chain is fitted to its readings. Backlash is a chain candidate
# already; naming it only asks that the record models it.
EFFECT_PARAMS: dict[str, tuple[ParamKey, ...]] = {
    "periodic_error": (
        ("periodic_error", "x_sin_deg"),
        ("periodic_error", "x_cos_deg"),
        ("periodic_error", "y_sin_deg"),
        ("periodic_error", "y_cos_deg"),
    ),
    "backlash": (("backlash", "x_deg"), ("backlash", "y_deg")),
    "sensor_nonlinearity": (
        ("sensor_nonlinearity", "ref_x_per_deg"),
        ("sensor_nonlinearity", "ref_y_per_deg"),
    ),
    "temperature_drift": (
        ("temperature_drift", "ref_x_deg_per_k"),
        ("temperature_drift", "ref_y_deg_per_k"),
        ("temperature_drift", "ref_scale_per_k"),
    ),
    "time_drift": (("time_drift", "ref_x_deg_per_h"), ("time_drift", "ref_y_deg_per_h")),
}
EXTRA_EFFECTS = tuple(EFFECT_PARAMS)
# The reference sensor's own reading errors among them: what the record then knows of its reference.
REFERENCE_EFFECTS = ("sensor_nonlinearity", "temperature_drift", "time_drift")
# Pairs that are one physical quantity (a worm's amplitude and phase): both are determined, or
# neither is fitted.
PAIRED: dict[ParamKey, ParamKey] = {
    ("periodic_error", "x_sin_deg"): ("periodic_error", "x_cos_deg"),
    ("periodic_error", "x_cos_deg"): ("periodic_error", "x_sin_deg"),
    ("periodic_error", "y_sin_deg"): ("periodic_error", "y_cos_deg"),
    ("periodic_error", "y_cos_deg"): ("periodic_error", "y_sin_deg"),
}
IN_CHAIN = ("offaxis_coupling",)
# The bench's drawings: standard uncertainties of the geometric parameters a stage bench is built to
# (a tilt or an axis seated on machined faces and locating pins is square to about half a degree). A
# parameter the points determine worse than PRIOR_WHEN times this is fitted with it as a prior
# (fit_chain).
PRIOR_SD: dict[str, float] = {"axis_misalignment": 0.5, "mounting_tilt": 0.5, "sensor_yaw": 0.5}
PRIOR_WHEN = 0.5
ESSENTIAL = (
    ("stage_scale", "x"),
    ("stage_scale", "y"),
    ("mounting_tilt", "desk_x_deg"),
    ("mounting_tilt", "desk_y_deg"),
)
REF_OBS = REF


def unit_of(key: ParamKey) -> str:
    return param_unit(key)


# --- identifiability -------------------------------------------------------------------------
@dataclass
class Selection:
    kept: list[int]
    fixed: list[int]
    merged_into: dict[int, list[tuple[int, float]]]  # fixed index -> [(kept index, coefficient)]
    rel_residual: list[float]


def select_identifiable(
    J: NDArray[np.float64], scales: NDArray[np.float64], rel_tol: float = IDENTIFIABLE_REL
) -> Selection:
    """Greedy column selection in candidate order: keep a column if it adds a new direction."""
    Js = J * scales
    kept: list[int] = []
    fixed: list[int] = []
    merged: dict[int, list[tuple[int, float]]] = {}
    rels = []
    # a column this much smaller than the largest is rounding, not signal (sin(π·k) of a worm
    # sampled at two phases)
    floor = UNEXERCISED_REL * float(np.max(np.linalg.norm(Js, axis=0), initial=0.0))
    for i in range(Js.shape[1]):
        col = Js[:, i]
        norm = float(np.linalg.norm(col))
        if norm <= floor:
            rels.append(0.0)
            fixed.append(i)
            merged[i] = []
            continue
        if kept:
            basis = Js[:, kept]
            coef = np.linalg.lstsq(basis, col, rcond=None)[0]
            rel = float(np.linalg.norm(col - basis @ coef)) / norm
        else:
            coef, rel = np.zeros(0), 1.0
        rels.append(rel)
        if rel > rel_tol:
            kept.append(i)
        else:
            fixed.append(i)
            # physical coefficients: a change d of parameter i looks like changes coef_j * s_i / s_j
            # of kept j
            merged[i] = [
                (kept[j], float(coef[j] * scales[i] / scales[kept[j]]))
                for j in range(len(kept))
                if abs(coef[j]) > 0.05 * np.max(np.abs(coef))
            ]
    return Selection(kept, fixed, merged, rels)


def numeric_jacobian(
    fun: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    x0: NDArray[np.float64],
    scales: NDArray[np.float64],
) -> NDArray[np.float64]:
    """The chain's Jacobian for identifiability and covariance: the one finite-difference rule,
    stepping a thousandth of each parameter's typical magnitude (the linearisation the selection
    judges)."""
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
    # effects asked for whose parameters these points determine none of -> why (every parameter held
    # at zero)
    undetermined: dict[str, str] = field(default_factory=dict)
    # parameters fitted with a prior from the bench's drawings (the points alone determine them
    # worse) -> why
    priors: dict[ParamKey, str] = field(default_factory=dict)


def worm_phases(bench: StageBench, cmd_deg: NDArray[np.float64], axis: str) -> int:
    """How many distinct phases of the stage's worm the commands sample (to a hundredth of a
    turn)."""
    qx, qy = bench.quantise(cmd_deg, cmd_deg)
    period = bench.worm_period_x_deg if axis == "x" else bench.worm_period_y_deg
    turns = (qx if axis == "x" else qy) / period
    return int(np.unique(np.round((turns % 1.0) * 100) % 100).size)


def _worm_reason(ax: str, bench: StageBench, pts: StagePoints) -> str | None:
    """A worm seen at too few phases: its periodic error looks like the stage's scale and zero."""
    cmd = pts.stage_x_deg if ax == "x" else pts.stage_y_deg
    period = bench.worm_period_x_deg if ax == "x" else bench.worm_period_y_deg
    n = worm_phases(bench, cmd, ax)
    return (
        f"the points sample the {ax} stage's worm (period {period:.6g} deg) at {n} "
        f"phase{'s' * (n != 1)}: too few to tell its periodic error's amplitude and phase "
        f"from the stage's scale and zero; held at 0 (a scan of the {ax} stage in steps of "
        "an eighth of the period determines it)"
    )


def _backlash_reason(ax: str, bench: StageBench, pts: StagePoints) -> str | None:
    """A stage approached from one side only: its lost motion is a constant, part of the zero."""
    direction = pts.dir_x if ax == "x" else pts.dir_y
    if not (np.any(direction > 0) and np.any(direction < 0)):
        return (
            f"every point was approached moving the {ax} stage the same way, so its lost "
            "motion is a constant "
            "the zero already holds; held at 0 (points approached from both sides determine it)"
        )
    return None


def _temperature_reason(ax: str, bench: StageBench, pts: StagePoints) -> str | None:
    """Points at one temperature: nothing to fit a temperature effect on."""
    if pts.temp_c is None or float(np.ptp(pts.temp_c)) < 0.05:
        return "the temperature hardly changed over the points; held at 0"
    return None


def _time_reason(ax: str, bench: StageBench, pts: StagePoints) -> str | None:
    """Points without a time: nothing to fit a drift on."""
    return "the points carry no time; held at 0" if pts.t_s is None else None


# the reason, in the lab's words, an effect's parameter is held where the points cannot determine it
_HELD_REASONS: dict[str, Callable[[str, StageBench, StagePoints], str | None]] = {
    "periodic_error": _worm_reason,
    "backlash": _backlash_reason,
    "temperature_drift": _temperature_reason,
    "time_drift": _time_reason,
}


def _held_reason(key: ParamKey, bench: StageBench, pts: StagePoints) -> str | None:
    """Why an effect parameter the points cannot determine is held, in the lab's words (None: the
    generic one)."""
    effect, name = key
    reason = _HELD_REASONS.get(effect)
    return None if reason is None else reason(name[:1], bench, pts)


def fit_chain(
    bench: StageBench,
    pts: StagePoints,
    ref_x: NDArray[np.float64],
    ref_y: NDArray[np.float64],
    loss: str = "linear",
    periodic: bool = False,
    max_nfev: int = 200,
    effects: Sequence[str] = (),
    worm_axes: Sequence[str] = ("x", "y"),
) -> ChainFit:
    """Least-squares fit of the identifiable chain parameters to the reference readings, with the
    parameters of the extra `effects` (EFFECT_PARAMS) free as well, as far as the points determine
    them: the others are held at zero with the reason (a worm's sine/cosine pair is fitted together
    or not at all). A periodic error is fitted on the stages of `worm_axes` only (those a diagnosis
    saw it on)."""
    wanted = _wanted_effects(effects, periodic)
    candidates, not_seen = _candidates(wanted, worm_axes)
    sel = _selection(bench, pts, candidates)
    kept, alone = _paired_only(sel.kept, candidates)
    free = [candidates[i] for i in kept]
    fixed: dict[ParamKey, str] = {
        candidates[i]: _why_held(i, candidates, sel, alone, wanted, bench, pts)
        for i in sorted(set(range(len(candidates))) - set(kept))
    }
    for key in not_seen:
        fixed[key] = (
            f"the diagnosis saw no worm error on the {key[1][:1]} stage (its terms within three "
            "standard uncertainties of zero); held at 0"
        )
    undetermined = _undetermined(wanted, fixed)
    model = StageEffectModel(bench, {}, free)
    observed = {"ref_x_deg": ref_x, "ref_y_deg": ref_y}
    fit = _fit_or_refuse(model, pts, observed, np.zeros(len(free)), loss, max_nfev)
    _check_fit(fit)
    sd = np.sqrt(np.clip(np.diag(fit.covariance), 1e-300, None))
    corr = fit.covariance / np.outer(sd, sd)
    pairs = _correlated_pairs([param_label(key) for key in free], corr)
    priors, prior_sd = _priors(free, sd, corr)
    if priors:
        start = np.where([prior is None for prior in prior_sd], fit.values, 0.0)
        fit = _fit_or_refuse(
            model, pts, observed, start, loss, max_nfev, prior_sd=prior_sd, prior_sigma=fit.sigma
        )
    return ChainFit(
        free,
        fit.values,
        fit.covariance,
        fixed,
        fit.residuals,
        fit.sigma,
        fit.dof,
        fit.converged,
        fit.nfev,
        fit.jac_singular_values,
        pairs,
        undetermined,
        priors,
    )


def _wanted_effects(effects: Sequence[str], periodic: bool) -> list[str]:
    """The extra effects asked for, each once (`periodic` asks for the worm's); others refused."""
    unknown = [
        effect for effect in effects if effect not in EXTRA_EFFECTS and effect not in IN_CHAIN
    ]
    if unknown:
        raise InputError(
            f"effects: {', '.join(unknown)} cannot be added to the kinematic chain; it takes "
            f"{', '.join(EXTRA_EFFECTS)} (and has {', '.join(IN_CHAIN)} already)"
        )
    wanted = (["periodic_error"] if periodic else []) + [
        effect for effect in effects if effect in EXTRA_EFFECTS
    ]
    return list(dict.fromkeys(wanted))


def _candidates(
    wanted: list[str], worm_axes: Sequence[str]
) -> tuple[list[ParamKey], list[ParamKey]]:
    """The chain's candidates and the wanted effects' parameters; and the worm terms left out."""
    not_seen = [
        k
        for k in EFFECT_PARAMS["periodic_error"]
        if "periodic_error" in wanted and k[1][:1] not in worm_axes
    ]
    candidates = list(CHAIN_CANDIDATES) + [
        k
        for effect in wanted
        for k in EFFECT_PARAMS[effect]
        if k not in CHAIN_CANDIDATES and k not in not_seen
    ]
    return candidates, not_seen


def _paired_only(kept: list[int], candidates: list[ParamKey]) -> tuple[list[int], list[int]]:
    """The kept candidates less a worm term whose partner is not kept; and those left alone."""
    alone = [
        i
        for i in kept
        if candidates[i] in PAIRED and candidates.index(PAIRED[candidates[i]]) not in kept
    ]
    return [i for i in kept if i not in alone], alone


def _selection(bench: StageBench, pts: StagePoints, candidates: list[ParamKey]) -> Selection:
    """Which candidates these points separate; refused where an essential one is not."""
    all_model = StageEffectModel(bench, {}, candidates)
    scales = np.array([typical_scale(k) for k in candidates])

    def pred(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return all_model.predict(x, pts, REF_OBS).ravel()

    jacobian = numeric_jacobian(pred, np.zeros(len(candidates)), scales)
    sel = select_identifiable(jacobian, scales)
    missing = [candidates[i] for i in sel.fixed if candidates[i] in ESSENTIAL]
    if missing:
        what = ", ".join(param_label(k) for k in missing)
        raise DegenerateDataError(
            f"the stage points do not determine {what}: the data need both stages moved to "
            "several angles each, with points off both axes (e.g. a 3 x 3 grid or larger)"
        )
    return sel


def _why_held(
    i: int,
    candidates: list[ParamKey],
    sel: Selection,
    alone: list[int],
    wanted: list[str],
    bench: StageBench,
    pts: StagePoints,
) -> str:
    """Why candidate i is held at zero: its effect's own reason first, then the selection's."""
    key = candidates[i]
    into = sel.merged_into.get(i, [])
    if key[0] in wanted and (why := _held_reason(key, bench, pts)) is not None:
        return why
    if i in alone:
        return (
            f"its partner {param_label(PAIRED[key])} is not determined by these points, so "
            "the worm's amplitude and phase are not either; held at 0"
        )
    if into:
        parts = ", ".join(
            f"{param_label(candidates[j])} ({coef:+.2g} per unit)" for j, coef in into
        )
        return (
            f"not separable on these points from {parts} (relative residual "
            f"{sel.rel_residual[i]:.1e}); held at 0"
        )
    return "these points do not exercise it; held at 0"


def _undetermined(wanted: list[str], fixed: dict[ParamKey, str]) -> dict[str, str]:
    """The effects asked for whose every parameter is held, with the reasons (each said once)."""
    undetermined = {}
    for effect in wanted:
        held = [k for k in EFFECT_PARAMS[effect] if k in fixed]
        if len(held) == len(EFFECT_PARAMS[effect]):
            undetermined[effect] = "; ".join(
                dict.fromkeys(f"{param_label(k)}: {fixed[k]}" for k in held)
            )
    return undetermined


def _fit_or_refuse(
    model: StageEffectModel,
    pts: StagePoints,
    observed: dict[str, NDArray[np.float64]],
    x0: NDArray[np.float64],
    loss: str,
    max_nfev: int,
    prior_sd: list[float | None] | None = None,
    prior_sigma: float | None = None,
) -> StageEffectFit:
    """The chain's bench fit, its failure refused in the kinematic fit's words."""
    try:
        # robust scale: see fit_stage_effects
        fit = fit_stage_effects(
            model,
            pts,
            observed,
            x0=x0,
            loss=loss,
            max_nfev=max_nfev,
            prior_sd=prior_sd,
            prior_sigma=prior_sigma,
        )
    except FitError as exc:
        raise DegenerateDataError(f"the kinematic fit failed on these points: {exc}") from None
    return fit


def _check_fit(fit: StageEffectFit) -> None:
    """Refuse a fit that did not converge or has no finite covariance: the points do not pin it."""
    if not fit.converged:
        raise DegenerateDataError(
            f"the kinematic fit did not converge in {fit.nfev} evaluations ({fit.message}); "
            "the points do not pin the bench down: add points over both stages' ranges"
        )
    if not np.all(np.isfinite(fit.covariance)):
        raise DegenerateDataError(
            "the kinematic fit has no finite covariance: the points do not separate its parameters"
        )


def _correlated_pairs(labels: list[str], corr: NDArray[np.float64]) -> list[tuple[str, str, float]]:
    """The pairs of parameters correlated beyond ±0.95 (near-degenerate), as the notes name them."""
    return [
        (labels[i], labels[j], float(corr[i, j]))
        for i in range(len(labels))
        for j in range(i + 1, len(labels))
        if abs(corr[i, j]) > 0.95
    ]


def _priors(
    free: list[ParamKey], sd: NDArray[np.float64], corr: NDArray[np.float64]
) -> tuple[dict[ParamKey, str], list[float | None]]:
    """Which parameters to fit again with the drawings' prior, and why; the prior sd of each."""
    # What the points determine worse than the bench's drawings do is not stated as if they did:
    # such a parameter (a near-degenerate partner whose data-only u exceeds half the drawings'
    # tolerance) is fitted again with that tolerance as a prior, so its value and u are the
    # drawings' updated by the points (the well-determined combination is still the points');
    # repeated fits of one bench then agree within what they state.
    priors: dict[ParamKey, str] = {}
    prior_sd: list[float | None] = []
    for i, key in enumerate(free):
        tol = PRIOR_SD.get(key[0])
        if tol is not None and sd[i] > PRIOR_WHEN * tol:
            partners = [
                param_label(free[j]) for j in range(len(free)) if j != i and abs(corr[i, j]) > 0.9
            ]
            priors[key] = (
                f"the points determine it only to ±{sd[i]:.2g} {unit_of(key)} (standard uncertainty"
                + (f"; near-degenerate with {', '.join(partners)}" if partners else "")
                + f"), worse than the bench's drawings: fitted with the prior 0 ± {tol:g} "
                f"{unit_of(key)} (standard uncertainty; a stage or sensor seated on machined "
                "faces and locating pins)"
            )
            prior_sd.append(tol)
        else:
            prior_sd.append(None)
    return priors, prior_sd


# --- the chain run forwards and backwards (unquantised commands)
# ------------------------------------
def actual_angles_deg(
    fx: EffectSet,
    bench: StageBench,
    cmd_x: ArrayLike,
    cmd_y: ArrayLike,
    dir_x: ArrayLike = 0.0,
    dir_y: ArrayLike = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Stage angles reached for commands (no pulse rounding, no noise): the model's mean bench."""
    out = []
    for ax, cmd, direction, period in (
        ("x", cmd_x, dir_x, bench.worm_period_x_deg),
        ("y", cmd_y, dir_y, bench.worm_period_y_deg),
    ):
        cmd_deg = np.asarray(cmd, dtype=float)
        ang = (
            cmd_deg * (1.0 + fx.get("stage_scale", ax))
            - np.asarray(direction, dtype=float) * fx.get("backlash", f"{ax}_deg") / 2.0
        )
        amp = fx.get("periodic_error", f"{ax}_amp_deg")
        if amp:
            ang = ang + amp * np.sin(
                2 * np.pi * cmd_deg / period
                + np.radians(fx.get("periodic_error", f"{ax}_phase_deg"))
            )
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
        for (effect, param), value in values.items():
            if effect == "noise":
                continue
            eff.setdefault(effect, {})[param] = float(value)
        return cls(bench, EffectSet.from_mapping("stage", registry_effects(eff)))

    def tilt(
        self, cmd_x: ArrayLike, cmd_y: ArrayLike, dir_x: ArrayLike = 0.0, dir_y: ArrayLike = 0.0
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        ax, ay = actual_angles_deg(self.fx, self.bench, cmd_x, cmd_y, dir_x, dir_y)
        readings = self.geometry.readings_deg(
            np.radians(np.atleast_1d(ax)), np.radians(np.atleast_1d(ay))
        )
        return readings["tilt_x"], readings["tilt_y"]

    def level(
        self,
        target_x: ArrayLike,
        target_y: ArrayLike,
        dir_x: ArrayLike = 1.0,
        dir_y: ArrayLike = 1.0,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Commands that bring the table to the wanted tilt: 2-D Newton from the ideal inverse."""
        tx = np.atleast_1d(np.asarray(target_x, dtype=float))
        ty = np.atleast_1d(np.asarray(target_y, dtype=float))
        y0 = ty.copy()
        x0 = offaxis_inverse_deg(tx, ty, clip=True)
        return newton_2d(lambda u, v: self.tilt(u, v, dir_x, dir_y), tx, ty, x0, y0)


# --- the measurement sensor fit
# --------------------------------------------------------------------
@dataclass
class MeasFit:
    names: list[str]  # free
    values: NDArray[np.float64]  # all MEAS_PARAMS, fixed ones at 0
    covariance: NDArray[np.float64]  # over `names`
    fixed: dict[str, str]
    residuals: dict[str, NDArray[np.float64]]
    sigma: float  # the residuals' rms over both axes (the reading-noise fallback)
    dof: int  # its degrees of freedom
    converged: bool
    nfev: int
    correlations: list[tuple[str, str, float]]
    covariance_dof: float = float("inf")  # of the covariance: each axis's variance over n − p/2


def _per_axis_covariance(
    J: NDArray[np.float64], r: NDArray[np.float64], n: int, p: int
) -> tuple[NDArray[np.float64], float]:
    """The parameters' covariance, and its degrees of freedom, of a least-squares fit whose first n
    residuals are the x axis's and the next n the y axis's, each axis with its own residual variance
    (the sandwich (JᵀJ)⁻¹ Jᵀ Σ J (JᵀJ)⁻¹, Σ diagonal with s_x² on the x rows and s_y² on the y rows,
    each from its axis's residuals over n − p/2 degrees of freedom). One variance pooled over both
    axes understates the parameters that the noisier axis determines (and overstates the others)
    whenever the two axes' point means scatter differently, as they do where one stage makes the
    longer moves between points."""
    dof_axis = max(n - p / 2.0, 1.0)
    var = np.concatenate(
        [np.full(n, float(r[:n] @ r[:n]) / dof_axis), np.full(n, float(r[n:] @ r[n:]) / dof_axis)]
    )
    bread = np.linalg.inv(J.T @ J)
    return np.asarray(bread @ (J.T * var) @ J @ bread, dtype=np.float64), dof_axis


def fit_meas(
    ref_x: NDArray[np.float64],
    ref_y: NDArray[np.float64],
    meas_x: NDArray[np.float64],
    meas_y: NDArray[np.float64],
    sign: NDArray[np.float64],
    loss: str = "linear",
    max_nfev: int = 200,
) -> MeasFit:
    """Mounting of the measurement sensor in the reference frame, from its readings against the
    reference's.

    The two sensors ride on one rigid table, so no stage parameter enters: meas = f(ref) exactly
    up to noise. Regressing on the reference (not on the stage commands) keeps stage
    repeatability out of the fit.
    """
    all_names = [meas_param[0] for meas_param in MEAS_PARAMS]
    scales = np.array([meas_param[2] for meas_param in MEAS_PARAMS])
    obs: NDArray[np.float64] = np.concatenate([meas_x, meas_y])

    def pred_all(p: NDArray[np.float64]) -> NDArray[np.float64]:
        meas_a, meas_b = meas_forward(p, sign, ref_x, ref_y)
        return np.concatenate([meas_a, meas_b])

    jacobian = numeric_jacobian(pred_all, np.zeros(len(all_names)), scales)
    sel = select_identifiable(jacobian, scales)
    kept = sel.kept
    fixed = _meas_held(sel, all_names)
    if len(obs) <= len(kept):
        raise DegenerateDataError(
            f"{len(meas_x)} points are too few for the {len(kept)} parameters of the "
            "measurement sensor's mounting"
        )

    def full(q: NDArray[np.float64]) -> NDArray[np.float64]:
        params = np.zeros(len(all_names))
        params[kept] = q
        return params

    def resid(q: NDArray[np.float64]) -> NDArray[np.float64]:
        return pred_all(full(q)) - obs

    sol = _meas_least_squares(resid, np.zeros(len(kept)), scales[kept], loss, max_nfev)
    residual = resid(sol.x)
    dof = max(residual.size - len(kept), 1)
    s2 = float(residual @ residual) / dof
    Jk = numeric_jacobian(lambda q: pred_all(full(q)), sol.x, scales[kept])
    sv = np.linalg.svd(Jk * scales[kept], compute_uv=False)
    if sv[-1] <= 1e-8 * sv[0]:
        raise DegenerateDataError(
            "the points do not separate the measurement sensor's mounting parameters"
        )
    n = len(meas_x)
    cov, cov_dof = _per_axis_covariance(Jk, residual, n, len(kept))
    sd = np.sqrt(np.diag(cov))
    corr = cov / np.outer(sd, sd)
    names = [all_names[i] for i in kept]
    pairs = _correlated_pairs(names, corr)
    return MeasFit(
        names,
        full(sol.x),
        cov,
        fixed,
        {"meas_x_deg": residual[:n], "meas_y_deg": residual[n:]},
        float(np.sqrt(s2)),
        dof,
        True,
        int(sol.nfev),
        pairs,
        cov_dof,
    )


def _meas_held(sel: Selection, all_names: list[str]) -> dict[str, str]:
    """Why each mounting parameter the points cannot separate is held: what it merges into."""
    fixed = {}
    for i in sel.fixed:
        into = ", ".join(f"{all_names[j]} ({coef:+.2g} per unit)" for j, coef in sel.merged_into[i])
        fixed[all_names[i]] = (
            f"not separable on these points from {into or 'the others'} "
            f"(relative residual {sel.rel_residual[i]:.1e}); held at 0"
        )
    return fixed


def _meas_least_squares(
    resid: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    q0: NDArray[np.float64],
    x_scale: NDArray[np.float64],
    loss: str,
    max_nfev: int,
) -> OptimizeResult:
    """The mounting's least squares (a robust loss scaled by a plain fit's); refused unconverged."""
    kw = {}
    if loss != "linear":
        pre = least_squares(resid, q0, x_scale=x_scale, method="trf", max_nfev=max_nfev)
        kw["f_scale"] = robust_scale(pre.fun)
        q0 = pre.x
    sol = least_squares(
        resid,
        q0,
        x_scale=x_scale,
        loss=loss,
        method="trf",
        max_nfev=max_nfev,
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
        **kw,
    )
    if not sol.status > 0 or not np.all(np.isfinite(sol.x)):
        raise DegenerateDataError(
            f"the measurement-sensor fit did not converge ({sol.message}); "
            "the points do not determine its mounting"
        )
    return sol
