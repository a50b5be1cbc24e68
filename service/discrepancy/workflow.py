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

import numpy as np
from numpy.typing import NDArray

from service.discrepancy import stats
from service.discrepancy.model import Family, Fit
from service.discrepancy.noise import NoiseLevel, from_residual
from service.discrepancy.report_types import (
    CandidateScore,
    DiscrepancyReport,
    EffectReason,
    FinalVsNoise,
    GoodnessOfFit,
    Magnitude,
    ReportExtra,
    ReportInputs,
    StepReport,
)
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
    scores: list[CandidateScore]
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
    skipped: list[EffectReason]
    already_in_model: list[EffectReason]
    notes: list[str]
    noise: NoiseLevel
    stop_scores: list[CandidateScore]
    stop_reason: str
    structure_final: list[stats.StructureTest]
    where_first: list[str]
    alpha: float
    extra: ReportExtra = field(default_factory=lambda: ReportExtra())

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
    skipped = _skips_asked_for(skips, candidates)
    notes: list[str] = []
    remaining = _separable_candidates(family, base, candidates, skips, explain_drop, skipped, notes)
    noise_var, noise_df = _noise_var(noise)
    fits = [base]
    steps: list[Step] = []
    current = base
    struct_now = structure(current.residuals)
    stop_scores: list[CandidateScore] = []
    stop_reason = ""
    while remaining and len(steps) < max_steps:
        testable = _testable(family, current, remaining, skipped)
        remaining = [effect for effect in remaining if effect in testable]
        m = max(len(testable), 1)
        tried, scores = _try_candidates(family, current, testable, alpha / m, noise_var, noise_df)
        winner = _best_significant(tried)
        if winner is None:
            stop_scores = scores
            stop_reason = _stop_sentence(tried, alpha, m)
            break
        effect, f1, sig = winner
        struct_after = structure(f1.residuals)
        steps.append(Step(effect, current, f1, sig, scores, struct_now, struct_after))
        fits.append(f1)
        current, struct_now = f1, struct_after
        if effect not in repeatable:
            remaining.remove(effect)
    if not stop_reason:
        stop_reason = _ran_out_sentence(remaining, max_steps)
    separability = _final_separability(family, current, remaining, notes)
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
        _already_in_model(family),
        notes,
        noise,
        stop_scores,
        stop_reason,
        struct_now,
        where_first,
        alpha,
        {"separability": separability},
    )


def _skips_asked_for(skips: dict[str, str], candidates: tuple[str, ...]) -> list[EffectReason]:
    """The family's up-front skips, as the report lists them, of the candidates asked for."""
    return [
        {"effect": effect, "reason": reason}
        for effect, reason in skips.items()
        if effect in candidates
    ]


def _already_in_model(family: Family) -> list[EffectReason]:
    """The effects the baseline represents already, with the reason, as the report lists them."""
    return [
        {"effect": effect, "reason": reason}
        for effect, reason in getattr(family, "already_in_model", {}).items()
    ]


def _best_significant(
    tried: list[tuple[str, Fit | None, stats.Significance]],
) -> tuple[str, Fit, stats.Significance] | None:
    """The step's winner: of the significant refits, the largest BIC gain (then the smallest p);
    None when no candidate passes."""
    winners = [
        (effect, fit, sig) for effect, fit, sig in tried if fit is not None and sig.significant
    ]
    if not winners:
        return None
    return min(winners, key=lambda t: (t[2].delta_bic, t[2].p_value))


def _ran_out_sentence(remaining: list[str], max_steps: int) -> str:
    """Why the selection ended when no step failed: nothing left to add, or the step limit."""
    return (
        "no further effect: every candidate the data can support is in the model"
        if not remaining
        else f"stopped after {max_steps} steps"
    )


def _candidate_labels(family: Family, base: Fit, effect: str) -> tuple[str, ...]:
    """Every parameter a candidate would add to the baseline fit, before any is left out."""
    return [
        block for block in family.full_blocks(base.effects + (effect,)) if block.effect == effect
    ][-1].labels


def _separable_candidates(
    family: Family,
    base: Fit,
    candidates: tuple[str, ...],
    skips: dict[str, str],
    explain_drop: Callable[[str, str], str | None] | None,
    skipped: list[EffectReason],
    notes: list[str],
) -> list[str]:
    """The candidates the baseline leaves room for: a candidate none of whose parameters the
    baseline fit can tell from its own is skipped; parameters it cannot tell are left out, with
    a note (both appended to `skipped` and `notes`)."""
    remaining: list[str] = []
    for effect in candidates:
        if effect in skips:
            continue
        frac = family.separability(base, effect)
        labels = _candidate_labels(family, base, effect)
        keep = tuple(lab for lab, lab_frac in zip(labels, frac) if lab_frac >= SEPARABLE_MIN)
        if not keep:
            skipped.append(
                {
                    "effect": effect,
                    "reason": "not separable from the baseline on these data: "
                    f"{100 * (1 - max(frac, default=0)):.2f} % or more of its signature is a "
                    "change of the baseline's own parameters (the grid does not sample it)",
                }
            )
            continue
        dropped = [lab for lab in labels if lab not in keep]
        if dropped:
            family.active[effect] = keep
            notes += _drop_notes(effect, dropped, explain_drop)
        remaining.append(effect)
    return remaining


def _drop_notes(
    effect: str, dropped: list[str], explain_drop: Callable[[str, str], str | None] | None
) -> list[str]:
    """One note per parameter left out of a candidate, with the family's reason when it has one."""
    notes = []
    for lab in dropped:
        why = explain_drop(effect, lab) if explain_drop else None
        notes.append(
            f"{effect}: parameter {lab} left out: "
            + (why or "not separable from the baseline on these data")
        )
    return notes


def _testable(
    family: Family, current: Fit, remaining: list[str], skipped: list[EffectReason]
) -> list[str]:
    """The remaining candidates that leave enough residual degrees of freedom to be tested; the
    others are appended to `skipped` with the count that rules them out."""
    testable = []
    for effect in remaining:
        k_new = (
            current.k
            + sum(block.size for block in family.blocks(current.effects + (effect,)))
            - sum(block.size for block in family.blocks(current.effects))
        )
        if family.n_obs - k_new < MIN_DOF_LEFT:
            left = family.n_obs - k_new
            skipped.append(
                {
                    "effect": effect,
                    "reason": f"too few points: {family.n_obs} readings leave {left} "
                    f"degree{'s' * (left != 1)} of freedom for a model with {k_new} parameters "
                    f"(at least {MIN_DOF_LEFT} needed)",
                }
            )
            continue
        testable.append(effect)
    return testable


def _try_candidates(
    family: Family,
    current: Fit,
    testable: list[str],
    level: float,
    noise_var: float | None,
    noise_df: float,
) -> tuple[list[tuple[str, Fit | None, stats.Significance]], list[CandidateScore]]:
    """One selection step: each testable candidate added to the current model in turn and
    tested at the corrected `level`; what was tried, and the scores the report shows."""
    tried: list[tuple[str, Fit | None, stats.Significance]] = []
    scores: list[CandidateScore] = []
    for effect in testable:
        outcome, score = _try_candidate(family, current, effect, level, noise_var, noise_df)
        if outcome is not None:
            tried.append(outcome)
        scores.append(score)
    return tried, scores


def _try_candidate(
    family: Family,
    current: Fit,
    effect: str,
    level: float,
    noise_var: float | None,
    noise_df: float,
) -> tuple[tuple[str, Fit | None, stats.Significance] | None, CandidateScore]:
    """Test one candidate: the one-step preview first, the nonlinear refit only when the preview
    does not already rule it out (no outcome when the refit fails)."""
    try:
        lin = family.linearised_fit(current, effect)
        pre = stats.nested_test(
            current.rss_w,
            current.k,
            lin.rss_w,
            lin.k,
            family.n_obs,
            level,
            noise_var,
            noise_df,
        )
    except (DegenerateDataError, FitError, np.linalg.LinAlgError, ValueError):
        pre = None
    if pre is not None and pre.p_value >= PRESCREEN_P:
        # far from significant even by the one-step preview: not worth a nonlinear fit
        return (effect, None, pre), {
            "effect": effect,
            "approximate": True,
            "rms_after": lin.rms(),
            "magnitude": _safe_magnitude(family, lin, effect),
            **pre.as_dict(),
        }
    try:
        f1 = family.fit(current.effects + (effect,), start=current)
    except (DegenerateDataError, FitError) as exc:
        return None, {"effect": effect, "error": str(exc)}
    sig = stats.nested_test(
        current.rss_w,
        current.k,
        f1.rss_w,
        f1.k,
        family.n_obs,
        level,
        noise_var,
        noise_df,
    )
    return (effect, f1, sig), {
        "effect": effect,
        "rms_after": f1.rms(),
        "magnitude": _safe_magnitude(family, f1, effect),
        **sig.as_dict(),
    }


def _final_separability(
    family: Family, current: Fit, remaining: list[str], notes: list[str]
) -> dict[str, dict[str, float]]:
    """How visible each remaining candidate's parameters are to the final model; a note (appended
    to `notes`) for each one too weakly visible to have shown."""
    separability: dict[str, dict[str, float]] = {}
    for effect in remaining:
        try:
            frac = family.separability(current, effect)
        except (DegenerateDataError, FitError, np.linalg.LinAlgError, ValueError):
            continue
        labels = family.blocks(current.effects + (effect,))[-1].labels
        separability[effect] = dict(zip(labels, frac))
        for lab, lab_frac in zip(labels, frac):
            if lab_frac < WEAK_SEPARABILITY:
                notes.append(_separability_note(family, effect, lab, lab_frac))
    return separability


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


def _safe_magnitude(family: Family, fit: Fit, effect: str) -> Magnitude:
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
    effect, _, sig = best
    why = []
    if sig.p_value >= alpha / m:
        why.append(f"p = {sig.p_value:.3g} is above the corrected level {alpha / m:.3g}")
    if sig.delta_bic >= 0:
        why.append(f"it does not lower the BIC (ΔBIC = {sig.delta_bic:+.1f})")
    return (
        f"no further effect: the most likely candidate, {effect}, is not significant "
        f"({'; '.join(why)}); the data hold nothing more these candidates can explain"
    )


def _rms(fit: Fit) -> list[float]:
    return [float(value) for value in fit.rms()]


def _step_report(family: Family, step: Step) -> StepReport:
    """One named effect as the report states it: its size, and the evidence that named it."""
    mag = family.magnitude(step.after, step.effect)
    return {
        "effect": step.effect,
        "rms_before": _rms(step.before),
        "rms_after": _rms(step.after),
        "magnitude": mag,
        "summary": magnitude_sentence(step.effect, mag),
        "evidence": {
            **step.significance.as_dict(),
            "rss_reduction_pct": 100.0
            * step.significance.delta_rss
            / max(step.before.rss_w, 1e-300),
            "candidates": step.scores,
            "where_before": stats.where_summary(step.structure_before),
            "structure_before": [test.as_dict() for test in step.structure_before],
            "structure_after": [test.as_dict() for test in step.structure_after],
        },
    }


def _final_vs_noise(res: Result, sigma: list[float]) -> FinalVsNoise:
    """Whether the final model leaves only noise: RMS over the noise level per axis, and the
    goodness-of-fit test against it."""
    final = res.final
    rss_w_final = float(np.sum((final.residuals / np.asarray(sigma)) ** 2))
    gof = stats.goodness_of_fit(
        rss_w_final,
        final.dof,
        res.noise.df if res.noise.source != "final residual" else float("inf"),
    )
    ratio = [
        float(rms / noise_sigma) if noise_sigma > 0 else None
        for rms, noise_sigma in zip(_rms(final), sigma)
    ]
    return {
        "rms_over_noise": ratio,
        **gof,
        "sentence": final_sentence(ratio, gof, res.noise.source),
    }


def to_report(res: Result, family: Family, inputs: ReportInputs | None = None) -> DiscrepancyReport:
    """The JSON report of docs/datasets.md (`discrepancy`), plus the evidence behind each step."""
    steps = [_step_report(family, step) for step in res.steps]
    final = res.final
    # the workflow sets it from the final residual when nothing else did
    assert res.noise.sigma is not None
    sigma = [float(value) for value in np.atleast_1d(res.noise.sigma)]
    report: DiscrepancyReport = {
        "format_version": 1,
        "kind": res.kind,
        "baseline": res.baseline,
        "unit": res.unit,
        "axes": list(res.axes),
        **(inputs or {}),
        "named_effects": res.named_effects,
        "chain": [res.baseline] + [step["effect"] for step in steps],
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
        "final_vs_noise": _final_vs_noise(res, sigma),
        "where": res.where_first,
        "where_final": stats.where_summary(res.structure_final),
        "structure_final": [test.as_dict() for test in res.structure_final],
        "stop": {"reason": res.stop_reason, "candidates": res.stop_scores},
        "alpha": res.alpha,
        "conclusion": conclusion(res, steps),
        **res.extra,
    }
    return report


def magnitude_sentence(effect: str, mag: Magnitude) -> str:
    parts = []
    for k, entry in mag.items():
        if not isinstance(entry, dict) or "value" not in entry:
            continue
        unit = "" if entry["unit"] == "1" else f" {entry['unit']}"
        parts.append(f"{k} = {_fmt(entry['value'])} ± {_fmt(entry['uncertainty'])}{unit}")
    return f"{effect}: " + "; ".join(parts)


def _fmt(x: float) -> str:
    return f"{x:.3g}" if x != 0 else "0"


def final_sentence(ratio: Sequence[float | None], gof: GoodnessOfFit, source: str) -> str:
    rs = ", ".join("n/a" if value is None else f"{value:.2f}" for value in ratio)
    if source == "final residual":
        return (
            "final residual is the noise level by construction (noise taken from it); "
            f"RMS/noise = {rs}"
        )
    p_value = gof.get("p_value")
    verdict = (
        "consistent with the noise level"
        if p_value is not None and p_value >= 0.01
        else "above the noise level: something no candidate describes is left"
    )
    return f"final RMS / noise = {rs} per axis; chi-square p = {p_value:.3g}: {verdict}"


def conclusion(res: Result, steps: list[StepReport]) -> str:
    if steps:
        chain = " → ".join([res.baseline] + [f"+ {step['effect']}" for step in steps])
        first = steps[0]["rms_before"]
        last = steps[-1]["rms_after"]
        gap = ", ".join(f"{before:.3g} → {after:.3g}" for before, after in zip(first, last))
        assert res.noise.sigma is not None
        return (
            f"{chain}: RMS {gap} {res.unit} per axis (noise "
            f"{', '.join(f'{sigma:.3g}' for sigma in np.atleast_1d(res.noise.sigma))} "
            f"{res.unit}, from the {res.noise.source}); {res.stop_reason}"
        )
    return f"the {res.baseline} baseline already describes the data: {res.stop_reason}"
