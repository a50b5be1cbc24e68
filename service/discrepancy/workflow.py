"""Fit the baseline, find where it disagrees with the data, name the missing effect, add it, repeat.

Forward selection over the candidate effects of docs/models.md §5 that the baseline lacks.
At each step every remaining candidate is added in turn and refitted; a candidate counts
when its extra-sum-of-squares test against the noise level passes at the Bonferroni-corrected
level (alpha over the number of candidates tested in that step) *and* it lowers the BIC. The
best of those (largest BIC gain) is named and kept. The loop ends when no candidate passes:
the report then says "no further effect" instead of inventing one.

Pure computation: no file I/O here (service.commands.discrepancy does that).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.discrepancy import stats
from service.discrepancy.model import Family, Fit
from service.discrepancy.noise import NoiseLevel, from_residual
from service.errors import DegenerateDataError, FitError

DEFAULT_ALPHA = 0.01  # family-wise level of one selection step
# a parameter whose signature the model absorbs to within this fraction is dropped
SEPARABLE_MIN = 1e-3
MIN_DOF_LEFT = 3  # a candidate must leave at least this many residual degrees of freedom
POOR_SEPARABILITY = 0.05  # below this fraction a remaining candidate is flagged as hard to see
# below this, the note says how much larger it must be to show, and what would help
WEAK_SEPARABILITY = 0.25
PRESCREEN_P = 0.05  # candidates whose one-step preview is above this p-value are not refitted


@dataclass
class Step:
    effect: str
    before: Fit
    after: Fit
    significance: stats.Significance
    scores: list[dict[str, Any]]
    structure_before: list[stats.StructureTest]
    structure_after: list[stats.StructureTest]


@dataclass
class Result:
    """Everything the JSON report and the report page are made of."""

    kind: str
    baseline: str
    unit: str
    axes: tuple[str, ...]
    fits: list[Fit]  # baseline, then after each named effect
    steps: list[Step]
    skipped: list[dict[str, Any]]
    already_in_model: list[dict[str, Any]]
    notes: list[str]
    noise: NoiseLevel
    stop_scores: list[dict[str, Any]]
    stop_reason: str
    structure_final: list[stats.StructureTest]
    where_first: list[str]
    alpha: float
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def final(self) -> Fit:
        return self.fits[-1]

    @property
    def named_effects(self) -> list[str]:
        out: list[str] = []
        for step in self.steps:
            if step.effect not in out:
                out.append(step.effect)
        return out


def _noise_var(noise: NoiseLevel) -> tuple[float | None, float]:
    """Variance of one noise-weighted residual (1 when the noise level is known) and its dof."""
    if noise.known:
        return 1.0, noise.df
    return None, float("inf")


def find_missing_effects(
    family: Family,
    candidates: tuple[str, ...],
    skips: dict[str, str],
    noise: NoiseLevel,
    structure: Callable[[NDArray[np.float64]], list[stats.StructureTest]],
    alpha: float = DEFAULT_ALPHA,
    repeatable: tuple[str, ...] = (),
    explain_drop: Callable[[str, str], str | None] | None = None,
    max_steps: int = 10,
) -> Result:
    """Run the workflow on one family; `structure(resid)` gives the residual structure tests."""
    base = family.fit(())
    skipped = [{"effect": e, "reason": r} for e, r in skips.items() if e in candidates]
    notes: list[str] = []
    remaining: list[str] = []
    for e in candidates:
        if e in skips:
            continue
        frac = family.separability(base, e)
        labels = [b for b in family.full_blocks(base.effects + (e,)) if b.effect == e][-1].labels
        keep = tuple(lab for lab, f in zip(labels, frac) if f >= SEPARABLE_MIN)
        if not keep:
            skipped.append(
                {
                    "effect": e,
                    "reason": "not separable from the baseline on these data: "
                    f"{100 * (1 - max(frac, default=0)):.2f} % or more of its signature is a "
                    "change of the baseline's own parameters (the grid does not sample it)",
                }
            )
            continue
        dropped = [lab for lab in labels if lab not in keep]
        if dropped:
            family.active[e] = keep
            for lab in dropped:
                why = explain_drop(e, lab) if explain_drop else None
                notes.append(
                    f"{e}: parameter {lab} left out: "
                    + (why or "not separable from the baseline on these data")
                )
        remaining.append(e)
    noise_var, noise_df = _noise_var(noise)
    fits = [base]
    steps: list[Step] = []
    current = base
    struct_now = structure(current.residuals)
    stop_scores: list[dict[str, Any]] = []
    stop_reason = ""
    while remaining and len(steps) < max_steps:
        scores = []
        tried: list[tuple[str, Fit | None, stats.Significance]] = []
        testable = []
        for e in remaining:
            k_new = (
                current.k
                + sum(b.size for b in family.blocks(current.effects + (e,)))
                - sum(b.size for b in family.blocks(current.effects))
            )
            if family.n_obs - k_new < MIN_DOF_LEFT:
                left = family.n_obs - k_new
                skipped.append(
                    {
                        "effect": e,
                        "reason": f"too few points: {family.n_obs} readings leave {left} "
                        f"degree{'s' * (left != 1)} of freedom for a model with {k_new} parameters "
                        f"(at least {MIN_DOF_LEFT} needed)",
                    }
                )
                continue
            testable.append(e)
        remaining = [e for e in remaining if e in testable]
        m = max(len(testable), 1)
        for e in testable:
            try:
                lin = family.linearised_fit(current, e)
                pre = stats.nested_test(
                    current.rss_w,
                    current.k,
                    lin.rss_w,
                    lin.k,
                    family.n_obs,
                    alpha / m,
                    noise_var,
                    noise_df,
                )
            except (DegenerateDataError, FitError, np.linalg.LinAlgError, ValueError):
                pre = None
            if pre is not None and pre.p_value >= PRESCREEN_P:
                # far from significant even by the one-step preview: not worth a nonlinear fit
                tried.append((e, None, pre))
                scores.append(
                    {
                        "effect": e,
                        "approximate": True,
                        "rms_after": lin.rms(),
                        "magnitude": _safe_magnitude(family, lin, e),
                        **pre.as_dict(),
                    }
                )
                continue
            try:
                f1 = family.fit(current.effects + (e,), start=current)
            except (DegenerateDataError, FitError) as exc:
                scores.append({"effect": e, "error": str(exc)})
                continue
            sig = stats.nested_test(
                current.rss_w,
                current.k,
                f1.rss_w,
                f1.k,
                family.n_obs,
                alpha / m,
                noise_var,
                noise_df,
            )
            tried.append((e, f1, sig))
            scores.append(
                {
                    "effect": e,
                    "rms_after": f1.rms(),
                    "magnitude": _safe_magnitude(family, f1, e),
                    **sig.as_dict(),
                }
            )
        winners = [(e, f, s) for e, f, s in tried if f is not None and s.significant]
        if not winners:
            stop_scores = scores
            stop_reason = _stop_sentence(tried, alpha, m)
            break
        e, f1, sig = min(winners, key=lambda t: (t[2].delta_bic, t[2].p_value))
        struct_after = structure(f1.residuals)
        steps.append(Step(e, current, f1, sig, scores, struct_now, struct_after))
        fits.append(f1)
        current, struct_now = f1, struct_after
        if e not in repeatable:
            remaining.remove(e)
    if not stop_reason:
        stop_reason = (
            "no further effect: every candidate the data can support is in the model"
            if not remaining
            else f"stopped after {max_steps} steps"
        )
    separability: dict[str, dict[str, float]] = {}
    for e in remaining:
        try:
            frac = family.separability(current, e)
        except (DegenerateDataError, FitError, np.linalg.LinAlgError, ValueError):
            continue
        labels = family.blocks(current.effects + (e,))[-1].labels
        separability[e] = dict(zip(labels, frac))
        for lab, f in zip(labels, frac):
            if f < WEAK_SEPARABILITY:
                notes.append(_separability_note(family, e, lab, f))
    if not noise.known:
        noise = from_residual(current.residuals, current.k)
    where_first = stats.where_summary(steps[0].structure_before if steps else struct_now)
    return Result(
        family.kind,
        family.baseline,
        family.unit,
        family.axes,
        fits,
        steps,
        skipped,
        [{"effect": e, "reason": r} for e, r in getattr(family, "already_in_model", {}).items()],
        notes,
        noise,
        stop_scores,
        stop_reason,
        struct_now,
        where_first,
        alpha,
        {"separability": separability},
    )


def _separability_note(family: Family, effect: str, label: str, frac: float) -> str:
    """Why a remaining candidate may be in the data unseen: a term only `frac` visible must be
    ~1/frac larger."""
    if frac < POOR_SEPARABILITY:
        text = (
            f"{effect}: parameter {label} is poorly separable from the final model: "
            f"{100 * (1 - frac):.1f} % of its signature (in norm) is a change of parameters "
            f"already fitted; only the remaining {100 * frac:.1f} % is visible to the test"
        )
    else:
        text = (
            f"{effect}: parameter {label} is only {100 * frac:.1f} % visible on these data (the "
            "rest of its signature is a change of parameters already fitted), so it shows only "
            f"when about {1 / frac:.0f} times larger than a term the data separate fully"
        )
    hint = family.separability_hints.get(effect)
    return f"{text}; {hint}" if hint else text


def _safe_magnitude(family: Family, fit: Fit, effect: str) -> dict[str, Any]:
    try:
        return family.magnitude(fit, effect)
    except (KeyError, ValueError, IndexError, ZeroDivisionError, FloatingPointError):
        return {}


def _stop_sentence(
    tried: list[tuple[str, Fit | None, stats.Significance]], alpha: float, m: int
) -> str:
    if not tried:
        return "no further effect: no candidate could be fitted"
    best = min(tried, key=lambda t: t[2].p_value)
    e, _, sig = best
    why = []
    if sig.p_value >= alpha / m:
        why.append(f"p = {sig.p_value:.3g} is above the corrected level {alpha / m:.3g}")
    if sig.delta_bic >= 0:
        why.append(f"it does not lower the BIC (ΔBIC = {sig.delta_bic:+.1f})")
    return (
        f"no further effect: the most likely candidate, {e}, is not significant "
        f"({'; '.join(why)}); the data hold nothing more these candidates can explain"
    )


def _rms(fit: Fit) -> list[float]:
    return [float(v) for v in fit.rms()]


def to_report(res: Result, family: Family, inputs: dict[str, Any] | None = None) -> dict[str, Any]:
    """The JSON report of docs/datasets.md (`discrepancy`), plus the evidence behind each step."""
    steps: list[dict[str, Any]] = []
    for s in res.steps:
        mag = family.magnitude(s.after, s.effect)
        steps.append(
            {
                "effect": s.effect,
                "rms_before": _rms(s.before),
                "rms_after": _rms(s.after),
                "magnitude": mag,
                "summary": magnitude_sentence(s.effect, mag),
                "evidence": {
                    **s.significance.as_dict(),
                    "rss_reduction_pct": 100.0
                    * s.significance.delta_rss
                    / max(s.before.rss_w, 1e-300),
                    "candidates": s.scores,
                    "where_before": stats.where_summary(s.structure_before),
                    "structure_before": [t.as_dict() for t in s.structure_before],
                    "structure_after": [t.as_dict() for t in s.structure_after],
                },
            }
        )
    final = res.final
    # the workflow sets it from the final residual when nothing else did
    assert res.noise.sigma is not None
    sigma = [float(v) for v in np.atleast_1d(res.noise.sigma)]
    noise_var, noise_df = (
        _noise_var(res.noise) if res.noise.source != "final residual" else (None, res.noise.df)
    )
    rss_w_final = float(np.sum((final.residuals / np.asarray(sigma)) ** 2))
    gof = stats.goodness_of_fit(
        rss_w_final,
        final.dof,
        res.noise.df if res.noise.source != "final residual" else float("inf"),
    )
    ratio = [float(r / s) if s > 0 else None for r, s in zip(_rms(final), sigma)]
    report = {
        "format_version": 1,
        "kind": res.kind,
        "baseline": res.baseline,
        "unit": res.unit,
        "axes": list(res.axes),
        **(inputs or {}),
        "named_effects": res.named_effects,
        "chain": [res.baseline] + [s["effect"] for s in steps],
        "steps": steps,
        "skipped": res.skipped,
        "already_in_model": res.already_in_model,
        "notes": res.notes,
        "noise_level": sigma,
        "noise_source": res.noise.source,
        "noise_detail": res.noise.detail,
        "noise_dof": None if np.isinf(res.noise.df) else res.noise.df,
        "baseline_rms": _rms(res.fits[0]),
        "final_rms": _rms(final),
        "final_vs_noise": {
            "rms_over_noise": ratio,
            **gof,
            "sentence": final_sentence(ratio, gof, res.noise.source),
        },
        "where": res.where_first,
        "where_final": stats.where_summary(res.structure_final),
        "structure_final": [t.as_dict() for t in res.structure_final],
        "stop": {"reason": res.stop_reason, "candidates": res.stop_scores},
        "alpha": res.alpha,
        "conclusion": conclusion(res, steps),
        **res.extra,
    }
    return report


def magnitude_sentence(effect: str, mag: dict[str, Any]) -> str:
    parts = []
    for k, v in mag.items():
        if not isinstance(v, dict) or "value" not in v:
            continue
        unit = "" if v["unit"] == "1" else f" {v['unit']}"
        parts.append(f"{k} = {_fmt(v['value'])} ± {_fmt(v['uncertainty'])}{unit}")
    return f"{effect}: " + "; ".join(parts)


def _fmt(x: float) -> str:
    return f"{x:.3g}" if x != 0 else "0"


def final_sentence(ratio: Sequence[float | None], gof: dict[str, Any], source: str) -> str:
    rs = ", ".join("n/a" if r is None else f"{r:.2f}" for r in ratio)
    if source == "final residual":
        return (
            "final residual is the noise level by construction (noise taken from it); "
            f"RMS/noise = {rs}"
        )
    p = gof.get("p_value")
    verdict = (
        "consistent with the noise level"
        if p is not None and p >= 0.01
        else "above the noise level: something no candidate describes is left"
    )
    return f"final RMS / noise = {rs} per axis; chi-square p = {p:.3g}: {verdict}"


def conclusion(res: Result, steps: list[dict[str, Any]]) -> str:
    if steps:
        chain = " → ".join([res.baseline] + [f"+ {s['effect']}" for s in steps])
        first = steps[0]["rms_before"]
        last = steps[-1]["rms_after"]
        gap = ", ".join(f"{a:.3g} → {b:.3g}" for a, b in zip(first, last))
        assert res.noise.sigma is not None
        return (
            f"{chain}: RMS {gap} {res.unit} per axis (noise "
            f"{', '.join(f'{s:.3g}' for s in np.atleast_1d(res.noise.sigma))} "
            f"{res.unit}, from the {res.noise.source}); {res.stop_reason}"
        )
    return f"the {res.baseline} baseline already describes the data: {res.stop_reason}"
