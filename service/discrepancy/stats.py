"""Statistics of the discrepancy workflow: significance of an added term and structure in residuals.

Why these tests: a candidate effect is a nested extension of the current model, so the
classical extra-sum-of-squares F-test (or its chi-square limit when the noise level is
known) says whether the drop in residual is more than noise could produce. The workflow
tests several candidates at each step, so the level is Bonferroni-corrected; a BIC gain
is required as well so that a large data set cannot make a negligible term "significant".

Distributions come from scipy.special (not scipy.stats, whose import alone costs more than
a whole workflow run).

Residual structure tests answer "where do model and measurement disagree": each one is a
regression of the residual on one covariate (stage-angle shape, approach direction,
temperature, time, worm phase) with a statistic and a p-value, not a judgement by eye.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import special

from service.discrepancy.report_types import (
    GoodnessOfFit,
    SignificanceJSON,
    StructureDetail,
    StructureTestJSON,
)


def chi2_sf(x: float, k: float) -> float:
    return float(special.chdtrc(k, max(x, 0.0)))


def f_sf(f: float, d1: float, d2: float) -> float:
    if not math.isfinite(f):
        return 0.0
    return float(special.fdtrc(d1, d2, max(f, 0.0)))


def t_two_sided(t: float, df: float) -> float:
    return float(2.0 * special.stdtr(df, -abs(t)))


def welch_t(a: NDArray[np.float64], b: NDArray[np.float64]) -> tuple[float, float]:
    """Welch's two-sample t statistic and two-sided p-value."""
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    se2 = va + vb
    if se2 <= 0:
        return 0.0, 1.0
    t = (a.mean() - b.mean()) / math.sqrt(se2)
    df = se2**2 / (va**2 / (a.size - 1) + vb**2 / (b.size - 1))
    return float(t), t_two_sided(t, df)


def pearson(x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[float, float]:
    """Pearson correlation and its two-sided p-value (t with n - 2 degrees of freedom)."""
    n = x.size
    xc, yc = x - x.mean(), y - y.mean()
    den = math.sqrt(float(xc @ xc) * float(yc @ yc))
    if den == 0 or n < 3:
        return 0.0, 1.0
    rho = max(-1.0, min(1.0, float(xc @ yc) / den))
    if abs(rho) >= 1.0:
        return rho, 0.0
    t = rho * math.sqrt((n - 2) / (1.0 - rho * rho))
    return rho, t_two_sided(t, n - 2)


@dataclass
class Significance:
    """Outcome of testing one added term against the noise level."""

    delta_rss: float  # drop of the (noise-weighted) residual sum of squares
    df_added: int  # parameters the term adds
    f_stat: float
    df_denominator: float  # inf when the noise level is taken as known
    p_value: float
    alpha: float  # per-test level after the multiple-comparison correction
    bic_before: float
    bic_after: float
    denominator_source: str  # "noise level" or "residual of the extended model"

    @property
    def delta_bic(self) -> float:
        return self.bic_after - self.bic_before

    @property
    def significant(self) -> bool:
        return bool(self.p_value < self.alpha and self.delta_bic < 0.0)

    def as_dict(self) -> SignificanceJSON:
        return {
            "delta_rss_weighted": self.delta_rss,
            "df_added": self.df_added,
            "f_stat": self.f_stat,
            "df_denominator": None if math.isinf(self.df_denominator) else self.df_denominator,
            "test": "chi2" if math.isinf(self.df_denominator) else "F",
            "p_value": self.p_value,
            "alpha": self.alpha,
            "bic_before": self.bic_before,
            "bic_after": self.bic_after,
            "delta_bic": self.delta_bic,
            "denominator": self.denominator_source,
            "significant": self.significant,
        }


def bic(rss_w: float, n_obs: int, k: int, noise_known: bool) -> float:
    """BIC of a least-squares fit: chi-square form when the noise is known, Gaussian likelihood
    otherwise."""
    if noise_known:
        return float(rss_w + k * math.log(n_obs))
    return float(n_obs * math.log(max(rss_w, 1e-300) / n_obs) + k * math.log(n_obs))


def nested_test(
    rss0: float,
    k0: int,
    rss1: float,
    k1: int,
    n_obs: int,
    alpha: float,
    noise_var: float | None,
    noise_df: float,
) -> Significance:
    """Extra-sum-of-squares test of model 1 (k1 parameters) against nested model 0 (k0 < k1).

    Residual sums of squares are noise-weighted when `noise_var` is given (then noise_var is
    the variance of a weighted residual, 1 for a known instrument noise, with `noise_df`
    degrees of freedom, inf when known exactly). The denominator is the larger of that noise
    variance and the residual variance of model 1, so structure that no candidate explains
    cannot be mistaken for the candidate that happens to absorb a bit of it.
    """
    df_added = k1 - k0
    dof1 = n_obs - k1
    if df_added <= 0 or dof1 <= 0:
        return Significance(0.0, max(df_added, 0), 0.0, max(dof1, 0), 1.0, alpha, 0.0, 0.0, "none")
    resid_var = rss1 / dof1
    known = noise_var is not None
    if noise_var is not None and noise_var >= resid_var:
        denom, df2, source = noise_var, noise_df, "noise level"
    else:
        denom, df2, source = resid_var, float(dof1), "residual of the extended model"
    drop = max(rss0 - rss1, 0.0)
    f_stat = (drop / df_added) / denom if denom > 0 else math.inf
    pv = chi2_sf(f_stat * df_added, df_added) if math.isinf(df2) else f_sf(f_stat, df_added, df2)
    scale = noise_var if noise_var is not None else 1.0
    return Significance(
        drop,
        df_added,
        float(f_stat),
        float(df2),
        pv,
        alpha,
        bic(rss0 / scale, n_obs, k0, known),
        bic(rss1 / scale, n_obs, k1, known),
        source,
    )


def goodness_of_fit(rss_w: float, dof: int, noise_df: float) -> GoodnessOfFit:
    """Is the final residual consistent with the noise level? (chi-square or F of the variance
    ratio)."""
    if dof <= 0:
        return {"reduced_chi2": None, "dof": dof, "p_value": None}
    ratio = rss_w / dof
    pv = chi2_sf(rss_w, dof) if math.isinf(noise_df) else f_sf(ratio, dof, noise_df)
    return {"reduced_chi2": float(ratio), "dof": int(dof), "p_value": pv}


# --- residual structure -----------------------------------------------------------------------


@dataclass
class StructureTest:
    axis: str
    covariate: str
    test: str
    statistic: float
    p_value: float
    sentence: str
    detail: StructureDetail = field(default_factory=lambda: StructureDetail())
    significant: bool = False

    def as_dict(self) -> StructureTestJSON:
        out: StructureTestJSON = {
            "axis": self.axis,
            "covariate": self.covariate,
            "test": self.test,
            "statistic": self.statistic,
            "p_value": self.p_value,
            "significant": self.significant,
            "sentence": self.sentence,
        }
        if self.detail:
            out["detail"] = self.detail
        return out


def _ols_f(
    r: NDArray[np.float64], base: NDArray[np.float64], extra: NDArray[np.float64]
) -> tuple[float, float, NDArray[np.float64], int]:
    """F-test of `extra` regressors on r beyond `base` regressors; returns F, p, coefficients,
    dof."""
    X0 = base
    X1 = np.column_stack([base, extra])
    n = r.size
    if n <= X1.shape[1] + 1:
        return 0.0, 1.0, np.zeros(extra.shape[1]), 0
    c0, *_ = np.linalg.lstsq(X0, r, rcond=None)
    c1, *_ = np.linalg.lstsq(X1, r, rcond=None)
    rss0 = float(np.sum((r - X0 @ c0) ** 2))
    rss1 = float(np.sum((r - X1 @ c1) ** 2))
    rank1 = np.linalg.matrix_rank(X1)
    rank0 = np.linalg.matrix_rank(X0)
    rank_added = rank1 - rank0
    dof = n - rank1
    if rank_added <= 0 or dof <= 0 or rss1 <= 0:
        return 0.0, 1.0, c1[X0.shape[1] :].astype(np.float64, copy=False), dof
    f_stat = ((rss0 - rss1) / rank_added) / (rss1 / dof)
    return (
        float(f_stat),
        f_sf(f_stat, rank_added, dof),
        c1[X0.shape[1] :].astype(np.float64, copy=False),
        int(dof),
    )


def shape_test(
    r: NDArray[np.float64],
    names: list[str],
    terms: NDArray[np.float64],
    axis: str,
    unit: str,
    describe: dict[str, str] | None = None,
) -> StructureTest:
    """Does the residual follow a smooth function of the stage angles (beyond what the model
    fitted)?"""
    base = np.ones((r.size, 1))
    f_stat, p_value, coef, _ = _ols_f(r, base, terms)
    # the single term that explains most on its own
    best, best_f = None, -1.0
    for j, nm in enumerate(names):
        fj, _, cj, _ = _ols_f(r, base, terms[:, j : j + 1])
        if fj > best_f:
            best, best_f, best_c, best_col = nm, fj, float(cj[0]), terms[:, j]
    desc = (describe or {}).get(best, best) if best is not None else ""
    span = float(np.ptp(best_c * best_col)) if best is not None else 0.0
    sentence = (
        f"{axis} residual follows {best} ({desc}): about {span:.3g} {unit} peak to peak over the "
        "grid"
        if best is not None
        else f"{axis} residual: no smooth shape"
    )
    return StructureTest(
        axis,
        "stage angles",
        "F (cubic polynomial in the stage angles)",
        f_stat,
        p_value,
        sentence,
        {"strongest_term": best, "strongest_term_span": span},
    )


def direction_test(
    r: NDArray[np.float64], d: NDArray[np.float64], axis: str, stage: str, unit: str
) -> StructureTest | None:
    """Welch t-test of the residual between the two approach directions of one stage."""
    plus, minus = r[d > 0], r[d < 0]
    if plus.size < 2 or minus.size < 2:
        return None
    t, p_value = welch_t(plus, minus)
    jump = float(plus.mean() - minus.mean())
    sentence = (
        f"{axis} residual jumps by {jump:.3g} {unit} with the approach direction of the {stage} "
        "stage (mean after a + move minus mean after a - move)"
    )
    return StructureTest(
        axis, f"dir_{stage}", "Welch t", float(t), float(p_value), sentence, {"jump": jump}
    )


def correlation_test(
    r: NDArray[np.float64],
    c: NDArray[np.float64],
    axis: str,
    covariate: str,
    what: str,
    per: str,
    unit: str,
) -> StructureTest | None:
    """Pearson correlation of the residual with a covariate, with the slope in the lab's units."""
    if c.size < 4 or np.ptp(c) <= 0 or np.ptp(r) <= 0:
        return None
    rho, pv = pearson(c, r)
    slope = float(np.polyfit(c, r, 1)[0])
    sentence = f"{axis} residual follows {what} (r = {rho:.2f}, slope {slope:.3g} {unit}/{per})"
    return StructureTest(
        axis,
        covariate,
        "Pearson r",
        rho,
        pv,
        sentence,
        {"slope": slope, "slope_unit": f"{unit}/{per}"},
    )


def runs_test(
    r: NDArray[np.float64], order: NDArray[np.float64], axis: str
) -> StructureTest | None:
    """Wald-Wolfowitz runs test of residual signs in time order: too few runs means slow wander."""
    centred = r[np.argsort(order, kind="stable")] - np.median(r)
    centred = centred[centred != 0]
    n1, n2 = int(np.sum(centred > 0)), int(np.sum(centred < 0))
    if n1 < 2 or n2 < 2:
        return None
    runs = 1 + int(np.sum(np.diff(np.sign(centred)) != 0))
    n = n1 + n2
    mu = 2.0 * n1 * n2 / n + 1.0
    var = 2.0 * n1 * n2 * (2.0 * n1 * n2 - n) / (n * n * (n - 1.0))
    if var <= 0:
        return None
    z = (runs - mu) / math.sqrt(var)
    p_value = float(special.ndtr(z))  # one-sided: wander gives too few runs
    sentence = (
        f"{axis} residual wanders slowly in time ({runs} runs of one sign where {mu:.0f} "
        "are expected)"
    )
    return StructureTest(
        axis,
        "t_s (order)",
        "runs (one-sided)",
        float(z),
        p_value,
        sentence,
        {"runs": runs, "expected": mu},
    )


def periodic_test(
    r: NDArray[np.float64],
    phase_rad: NDArray[np.float64],
    axis: str,
    stage: str,
    period_deg: float,
    unit: str,
) -> StructureTest | None:
    """Periodogram value of the residual at the worm period of one stage (sine and cosine
    regression)."""
    if r.size < 6:
        return None
    base = np.ones((r.size, 1))
    extra = np.column_stack([np.sin(phase_rad), np.cos(phase_rad)])
    if np.linalg.matrix_rank(np.column_stack([base, extra])) < 3:
        return None
    f_stat, p_value, coef, _ = _ols_f(r, base, extra)
    amp = float(np.hypot(*coef))
    sentence = (
        f"{axis} residual oscillates with the {stage} stage's worm period ({period_deg:g} deg of "
        f"stage angle), amplitude {amp:.3g} {unit}"
    )
    return StructureTest(
        axis,
        f"worm phase {stage}",
        "F (periodogram at the worm period)",
        f_stat,
        p_value,
        sentence,
        {"amplitude": amp, "period_deg": period_deg},
    )


def mark_significant(tests: list[StructureTest], alpha: float) -> list[StructureTest]:
    """Bonferroni over the tests of one residual set: flags what a metrologist should read first."""
    m = max(len(tests), 1)
    for t in tests:
        t.significant = bool(t.p_value < alpha / m)
    return tests


def where_summary(tests: list[StructureTest]) -> list[str]:
    """Sentences of the significant tests, strongest first; 'noise' when there are none."""
    sig = sorted((t for t in tests if t.significant), key=lambda t: t.p_value)
    if not sig:
        return ["no structure left: the residuals pass every test for a trend with the covariates"]
    return [f"{t.sentence} [p = {t.p_value:.2g}]" for t in sig]
