"""Fit effect parameters of the stacked-stage forward model to recorded points.

The model a lab fits is the simulator itself (service.physics.stage) with some effect
parameters free: the kinematic calibration and the discrepancy workflow's kinematic
baseline are both this fit with different free sets. Readings are predicted noise-free; the
covariance of the free parameters is the Gauss-Newton one, (JᵀJ)⁻¹ s², with s² the residual
variance per degree of freedom.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import OptimizeResult, least_squares

from service.errors import DegenerateDataError, FitError
from service.physics.effects import STAGE_EFFECTS, EffectSet
from service.physics.stage import StageBench, StageGeometry, simulate_stage

ParamKey = tuple[str, str]  # (effect, parameter)

# Parameters a fit uses in place of the registry's where the registry's are not linear: a worm's
# periodic error a·sin(φ) + b·cos(φ) of the worm phase φ per stage, the same term as the registry's
# amp·sin(φ + phase) with a = amp·cos(phase), b = amp·sin(phase). Amplitude and phase are singular
# at zero amplitude, where a fit starts (the phase then moves nothing); the pair is linear and
# determined wherever the points sample several phases.
FIT_PARAMS: dict[ParamKey, str] = {
    ("periodic_error", "x_sin_deg"): "deg",
    ("periodic_error", "x_cos_deg"): "deg",
    ("periodic_error", "y_sin_deg"): "deg",
    ("periodic_error", "y_cos_deg"): "deg",
}


def param_label(key: ParamKey) -> str:
    return f"{key[0]}.{key[1]}"


def param_unit(key: ParamKey) -> str:
    """The unit of a fitted parameter: the registry's, or that of the fit's own parametrisation."""
    return FIT_PARAMS[key] if key in FIT_PARAMS else STAGE_EFFECTS[key[0]].param(key[1]).unit


def typical_scale(key: ParamKey) -> float:
    """Magnitude used to scale a parameter in the solver (and its finite-difference step)."""
    if key in FIT_PARAMS:
        return 0.01  # a worm's periodic error: hundredths of a degree
    unit = param_unit(key)
    return {"deg": 0.1, "1": 1e-3, "1/deg": 1e-4, "deg/K": 1e-3, "1/K": 1e-4, "deg/h": 1e-2}.get(
        unit, 1e-2
    )


def registry_effects(effects: Mapping[str, Mapping[str, float]]) -> dict[str, dict[str, float]]:
    """Effect values in the registry's parameters (what the simulator takes): a periodic error's
    sine/cosine pair becomes its amplitude and phase."""
    out = {effect: dict(values) for effect, values in effects.items()}
    pe = out.get("periodic_error")
    if pe is not None:
        for ax in ("x", "y"):
            sin_term, cos_term = pe.pop(f"{ax}_sin_deg", None), pe.pop(f"{ax}_cos_deg", None)
            if sin_term is not None or cos_term is not None:
                sin_term, cos_term = sin_term or 0.0, cos_term or 0.0
                pe[f"{ax}_amp_deg"] = float(np.hypot(sin_term, cos_term))
                pe[f"{ax}_phase_deg"] = float(np.degrees(np.arctan2(cos_term, sin_term)))
    return out


@dataclass
class StagePoints:
    """The covariates of recorded stage points, with the defaults a missing column means."""

    stage_x_deg: NDArray[np.float64]
    stage_y_deg: NDArray[np.float64]
    dir_x: NDArray[np.float64]
    dir_y: NDArray[np.float64]
    temp_c: NDArray[np.float64] | None = None
    t_s: NDArray[np.float64] | None = None

    @classmethod
    def from_columns(cls, data: Mapping[str, NDArray[np.float64]]) -> StagePoints:
        x = np.asarray(data["stage_x_deg"], dtype=float)
        y = np.asarray(data["stage_y_deg"], dtype=float)
        z = np.zeros_like(x)
        return cls(
            x,
            y,
            np.asarray(data.get("dir_x", z), dtype=float),
            np.asarray(data.get("dir_y", z), dtype=float),
            None if "temp_c" not in data else np.asarray(data["temp_c"], dtype=float),
            None if "t_s" not in data else np.asarray(data["t_s"], dtype=float),
        )

    def __len__(self) -> int:
        return self.stage_x_deg.size


@dataclass
class StageEffectModel:
    """A bench with some effects fixed and others free: predicts sensor readings."""

    bench: StageBench
    fixed: dict[str, dict[str, float]]
    free: list[ParamKey]

    def effect_set(self, values: Iterable[float]) -> EffectSet:
        eff: dict[str, dict[str, float]] = {k: dict(value) for k, value in self.fixed.items()}
        for (effect, param), value in zip(self.free, values):
            eff.setdefault(effect, {})[param] = float(value)
        eff.pop("noise", None)
        return EffectSet.from_mapping("stage", registry_effects(eff))

    def predict(
        self, values: Iterable[float], pts: StagePoints, outputs: Sequence[str]
    ) -> NDArray[np.float64]:
        """Noise-free predictions (N, len(outputs)); outputs are column names such as ref_x_deg or
        tilt_x_deg."""
        fx = self.effect_set(values)
        sim = simulate_stage(
            self.bench,
            fx,
            pts.stage_x_deg,
            pts.stage_y_deg,
            pts.dir_x,
            pts.dir_y,
            pts.temp_c,
            pts.t_s,
            rng=None,
            geometry=StageGeometry.from_effects(self.bench, fx),
        )
        return np.column_stack([sim[output] for output in outputs])


@dataclass
class StageEffectFit:
    model: StageEffectModel
    values: NDArray[np.float64]
    covariance: NDArray[np.float64]
    residuals: dict[str, NDArray[np.float64]]
    sigma: float
    dof: int
    cost: float
    converged: bool
    nfev: int
    message: str
    jac_singular_values: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))

    def value(self, key: ParamKey) -> float:
        return float(self.values[self.model.free.index(key)])

    def std(self, key: ParamKey) -> float:
        i = self.model.free.index(key)
        return float(np.sqrt(max(self.covariance[i, i], 0.0)))

    @property
    def rss(self) -> float:
        return float(sum(np.sum(residual**2) for residual in self.residuals.values()))

    @property
    def n_obs(self) -> int:
        return int(sum(residual.size for residual in self.residuals.values()))


def robust_scale(residuals: NDArray[np.float64]) -> float:
    """Soft threshold of a robust loss: 3 x the MAD-based standard deviation of the residuals."""
    values = np.asarray(residuals, dtype=float)
    mad = float(np.median(np.abs(values - np.median(values))))
    return max(3.0 * 1.4826 * mad, 1e-5)


def fit_stage_effects(
    model: StageEffectModel,
    pts: StagePoints,
    observed: Mapping[str, NDArray[np.float64]],
    x0: Sequence[float] | NDArray[np.float64] | None = None,
    loss: str = "linear",
    f_scale: float | None = None,
    max_nfev: int = 2000,
    prior_sd: Sequence[float | None] | None = None,
    prior_sigma: float | None = None,
) -> StageEffectFit:
    """Least-squares fit of the free parameters to the observed columns (e.g. ref_x_deg, ref_y_deg).

    `prior_sd` (per free parameter, None for none) adds a prior N(0, sd²) to a parameter: one more
    residual x / sd weighed by `prior_sigma` (the readings' noise, from a fit without priors), so
    the covariance is the posterior's, s² (JᵀJ + s²/sd²)⁻¹, and the residuals and degrees of freedom
    stay the data's.
    """
    outputs = list(observed)
    obs = np.column_stack([np.asarray(observed[output], dtype=float) for output in outputs])
    n_obs, n_par = obs.size, len(model.free)
    if n_obs <= n_par:
        raise DegenerateDataError(
            f"{len(pts)} points give {n_obs} readings, fewer than the {n_par} free parameters "
            f"of the bench model ({', '.join(param_label(k) for k in model.free)})"
        )
    start = np.zeros(n_par) if x0 is None else np.asarray(x0, dtype=float)
    scales = np.array([typical_scale(k) for k in model.free])

    with_prior, prior_w = _prior_rows(prior_sd, prior_sigma)

    def data_resid(x: NDArray[np.float64]) -> NDArray[np.float64]:
        residual: NDArray[np.float64] = (model.predict(x, pts, outputs) - obs).ravel()
        return residual

    def resid(x: NDArray[np.float64]) -> NDArray[np.float64]:
        if not with_prior:
            return data_resid(x)
        return np.concatenate([data_resid(x), prior_w * x[with_prior]])

    if n_par == 0:
        data_res = resid(start)
        return _result(
            model,
            start,
            np.zeros((0, 0)),
            data_res,
            outputs,
            obs.shape,
            0.0,
            True,
            1,
            "no free parameters",
            None,
        )
    kw = {}
    if loss != "linear":
        if f_scale is None:
            f_scale, start = _robust_start(model, pts, observed, start, max_nfev)
        kw["f_scale"] = f_scale
    sol = _solve(resid, start, scales, loss, max_nfev, kw)
    jac = sol.jac
    data_res = sol.fun if loss == "linear" else resid(sol.x)
    data_res = data_res[:n_obs]  # the data's residuals (the prior rows are not readings)
    dof = max(n_obs - n_par, 1)
    s2 = float(data_res @ data_res) / dof
    sv = _singular_values(jac, scales, model.free)
    cov = _covariance(jac, n_obs, with_prior, prior_sd, s2)
    return _result(
        model,
        sol.x,
        cov,
        data_res,
        outputs,
        obs.shape,
        s2,
        bool(sol.status > 0),
        int(sol.nfev),
        str(sol.message),
        sv,
    )


def _prior_rows(
    prior_sd: Sequence[float | None] | None, prior_sigma: float | None
) -> tuple[list[int], NDArray[np.float64]]:
    """The parameters with a prior, and the weight of each prior's residual row (noise over sd)."""
    with_prior = [i for i, sd in enumerate(prior_sd or []) if sd]
    prior_w = (
        np.array(
            [float(prior_sigma or 0.0) / float((prior_sd or [])[i] or 1.0) for i in with_prior]
        )
        if with_prior
        else np.zeros(0)
    )
    return with_prior, prior_w


def _robust_start(
    model: StageEffectModel,
    pts: StagePoints,
    observed: Mapping[str, NDArray[np.float64]],
    start: NDArray[np.float64],
    max_nfev: int,
) -> tuple[float, NDArray[np.float64]]:
    """A robust fit's soft threshold and start, taken from a plain fit of the same points."""
    # Residuals at the starting bench are no guide to the scale of good residuals: fit plainly
    # first, take the scale robustly (MAD) from that fit, and start the robust fit there.
    pre = fit_stage_effects(model, pts, observed, x0=start, loss="linear", max_nfev=max_nfev)
    return robust_scale(np.concatenate(list(pre.residuals.values()))), pre.values


def _solve(
    resid: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    start: NDArray[np.float64],
    scales: NDArray[np.float64],
    loss: str,
    max_nfev: int,
    kw: dict[str, float],
) -> OptimizeResult:
    """scipy's least squares as the bench fit sets it; a failure or divergence is a FitError."""
    try:
        sol = least_squares(
            resid,
            start,
            x_scale=scales,
            diff_step=1e-4 * scales / np.maximum(np.abs(start), scales),
            loss=loss,
            method="trf",
            max_nfev=max_nfev,
            xtol=1e-12,
            ftol=1e-12,
            gtol=1e-12,
            **kw,
        )
    except ValueError as exc:
        raise FitError(f"bench fit failed: {exc}") from exc
    if not np.all(np.isfinite(sol.x)):
        raise FitError("bench fit diverged (non-finite parameters)")
    return sol


def _singular_values(
    jac: Any, scales: NDArray[np.float64], free: list[ParamKey]
) -> NDArray[np.float64]:
    """The scaled Jacobian's singular values, refused when they say the fit is singular."""
    sv: NDArray[np.float64] = np.linalg.svd(jac * scales, compute_uv=False)
    if sv[-1] <= 1e-8 * sv[0]:
        raise DegenerateDataError(
            "the data do not separate the free bench parameters "
            f"({', '.join(param_label(k) for k in free)}): the fit is singular"
        )
    return sv


def _covariance(
    jac: Any,
    n_obs: int,
    with_prior: list[int],
    prior_sd: Sequence[float | None] | None,
    s2: float,
) -> NDArray[np.float64]:
    """s²(JᵀJ)⁻¹ over the data's rows, each prior adding s²/sd² to its diagonal: the posterior's."""
    jtj = jac[:n_obs].T @ jac[:n_obs]
    if with_prior:
        jtj[with_prior, with_prior] += (
            s2 / np.array([float((prior_sd or [])[i] or 1.0) for i in with_prior]) ** 2
        )
    cov: NDArray[np.float64] = np.linalg.pinv(jtj) * s2
    return cov


def _result(
    model: StageEffectModel,
    x: ArrayLike,
    cov: NDArray[np.float64],
    r: ArrayLike,
    outputs: Sequence[str],
    shape: tuple[int, ...],
    s2: float,
    ok: bool,
    nfev: int,
    msg: str,
    sv: NDArray[np.float64] | None,
) -> StageEffectFit:
    rr = np.asarray(r).reshape(shape)
    res = {output: rr[:, i] for i, output in enumerate(outputs)}
    dof = max(rr.size - len(model.free), 1)
    return StageEffectFit(
        model,
        np.asarray(x, dtype=float),
        cov,
        res,
        float(np.sqrt(s2)),
        dof,
        float(np.sum(rr**2) / 2),
        ok,
        nfev,
        msg,
        np.zeros(0) if sv is None else sv,
    )
