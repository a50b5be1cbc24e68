"""Adopting a diagnosis: the kinematic calibration refitted on the same points with the named
effects switched on.

The last step of the workflow, shared by the daemon (`POST /diagnoses/{id}/adopt`) and the command
line (`tiltlab discrepancy --adopt MODEL.json`): the model it writes states which effects were added
and from which diagnosis, and `tiltlab correct`, `tiltlab level` and the daemon's levelling use them
like any other parameter.

Whether a named effect can be adopted is decided when it is named (`adoption`), by the very fit
adopting it makes: a diagnosis never offers an effect the refit then cannot separate. An effect the
points cannot determine is said so, with the reason and the measurement that would determine it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypedDict, cast

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from service.calibration.methods.stage.chain import (
    EFFECT_PARAMS,
    EXTRA_EFFECTS,
    IN_CHAIN,
    REFERENCE_EFFECTS,
)
from service.calibration.model import CalibrationModel, ParameterJSON, StageBenchJSON
from service.calibration.registry import FitOptions, get_method
from service.calibration.stage_effect_fit import param_label
from service.errors import DegenerateDataError, FitError, InputError
from service.physics.stage import StageBench

if TYPE_CHECKING:
    from service.discrepancy.workflow import Step

# a bench as the caller has it: the hardware, or its fields as a record's model states them
BenchGiven = StageBench | StageBenchJSON


class NothingToAdopt(InputError):
    """The diagnosis named no effect the calibration does not already have."""


class NotAdoptable(InputError):
    """Every effect the diagnosis named beyond the calibration's own is one these points cannot
    determine."""


# What would determine an effect the stored points cannot: the measurement, in the lab's words.
MEASUREMENTS = {
    "backlash": "the same points approached from above as well as from below (POST "
    "/records/{id}/diagnose with measure: true plans and runs it)",
    "periodic_error": "a scan of the stage in steps of an eighth of its worm's period over one "
    "period (measure: true plans and runs it)",
    "time_drift": "some of the points measured again later, in another order (measure: true plans "
    "and runs it)",
    "temperature_drift": "the points measured again at a temperature a few kelvin away; this bench "
    "cannot set its "
    "temperature: repeat the calibration when the room's temperature differs",
    "sensor_nonlinearity": "points over a wider range of tilts, towards the stages' travel "
    "(measure: true plans and runs it)",
}


class AdoptionVerdict(TypedDict):
    """An `Adoption` as a diagnosis stores and shows it."""

    effect: str
    adoptable: bool
    reason: str
    measurement: str | None
    axes: list[str] | None


class AdoptedFrom(TypedDict, total=False):
    """Where an adopted model's added effects come from, as its state keeps it: a diagnosis of a
    record (the daemon) or a report of a dataset (the command line); `what` says it in words."""

    id: int  # the diagnosis
    record_id: int
    sensor: str
    baseline: str
    measurement_job_ids: list[int]
    report: str  # the report file
    input: str  # the dataset
    what: str


@dataclass
class Adoption:
    """Whether one named effect can be added to the record, and if not why and what would make it
    so."""

    effect: str
    adoptable: bool
    reason: str
    measurement: str | None = None
    # a worm's periodic error: the stages it is fitted on (those it was seen on)
    axes: list[str] | None = None

    def as_dict(self) -> AdoptionVerdict:
        return {
            "effect": self.effect,
            "adoptable": self.adoptable,
            "reason": self.reason,
            "measurement": self.measurement,
            "axes": None if self.axes is None else list(self.axes),
        }


def record_effects(model: CalibrationModel | Mapping[str, object] | None) -> set[str]:
    """The effects a record's model fits already: those with a free parameter in its chain (adding
    them again would change nothing)."""
    if model is None:
        return set()
    doc = model.to_json_dict() if isinstance(model, CalibrationModel) else model
    # a stored model (MODEL.json) states its parameters so
    params = cast("Mapping[str, ParameterJSON]", doc.get("parameters", {}))
    have = set()
    for effect, keys in EFFECT_PARAMS.items():
        if any(
            param_label(k) in params and not params[param_label(k)].get("fixed", False)
            for k in keys
        ):
            have.add(effect)
    # a model fitted with amplitude and phase (before the sine/cosine pair) has its worm free too
    if any(
        name.startswith("periodic_error.") and not param.get("fixed", False)
        for name, param in params.items()
    ):
        have.add("periodic_error")
    return have


def _nothing_to_adopt(named: Sequence[str], have: set[str] | frozenset[str]) -> NothingToAdopt:
    """The refusal when every named effect is in the chain or the record already: what was named,
    and what the record fits."""
    already = [effect for effect in named if effect in have]
    return NothingToAdopt(
        "the diagnosis named no effect beyond what the kinematic calibration already has"
        + (f" ({', '.join(named)})" if named else "")
        + (f"; the record fits {', '.join(already)} already" if already else "")
        + ": there is nothing to adopt"
    )


def effects_to_add(
    named: Sequence[str], sensor: str, have: set[str] | frozenset[str] = frozenset()
) -> list[str]:
    """The named effects the calibration adds; NothingToAdopt when none is left, InputError for one
    it cannot add."""
    extra = [effect for effect in named if effect not in IN_CHAIN and effect not in have]
    if not extra:
        raise _nothing_to_adopt(named, have)
    _refuse_terms_not_taken(extra, sensor)
    return extra


def _refuse_terms_not_taken(extra: list[str], sensor: str) -> None:
    """InputError for an effect the kinematic record has no term for: one it does not take, or a
    term of the measurement sensor's own."""
    cannot = [effect for effect in extra if effect not in EXTRA_EFFECTS]
    if cannot:
        raise InputError(
            f"{', '.join(cannot)} cannot be added to the kinematic calibration (it takes "
            f"{', '.join(EXTRA_EFFECTS)})"
        )
    if sensor != "ref" and any(effect in REFERENCE_EFFECTS for effect in extra):
        own = [effect for effect in extra if effect in REFERENCE_EFFECTS]
        raise InputError(
            f"the diagnosis explained the measurement sensor's readings; {', '.join(own)} of "
            "that sensor is not a term of the kinematic record, whose correction of the "
            "measurement sensor is its mounting (zeros, scales, yaw, non-orthogonality, seat "
            "tilt): diagnose with sensor 'ref' for the bench's and the reference's effects"
        )


def adopted_model(
    columns: Mapping[str, NDArray[np.float64]],
    named: Sequence[str],
    sensor: str,
    bench: BenchGiven,
    bench_source: str,
    diagnosis: AdoptedFrom,
    have: set[str] | frozenset[str] = frozenset(),
    keep: Sequence[str] = (),
    worm_axes: Sequence[str] = ("x", "y"),
) -> CalibrationModel:
    """The kinematic calibration of `columns` with the diagnosis' named effects added (and `keep`,
    the effects the diagnosed record was adopted with; a worm's error on the stages of `worm_axes`);
    `diagnosis` says where they came from (kept in the model's state with the effects). NotAdoptable
    when the points determine none of an added effect's parameters."""
    effects = effects_to_add(named, sensor, have)
    kept = [effect for effect in keep if effect not in effects]
    model = _fit(columns, kept + effects, bench, bench_source, worm_axes)
    undetermined = model.fit.get("undetermined_effects") or {}
    if undetermined:
        raise NotAdoptable(
            "; ".join(
                f"{effect}: these points determine none of its parameters ({why})"
                for effect, why in undetermined.items()
            )
        )
    model.state["added_effects"] = kept + effects
    model.state["diagnosis"] = dict(diagnosis)
    model.notes.append(
        f"adopted from {diagnosis.get('what', 'a diagnosis')}: added {', '.join(effects)}"
        + (f" (and kept {', '.join(kept)}, which the diagnosed record had)" if kept else "")
    )
    return model


def _fit(
    columns: Mapping[str, NDArray[np.float64]],
    effects: Sequence[str],
    bench: BenchGiven,
    bench_source: str,
    worm_axes: Sequence[str] = ("x", "y"),
) -> CalibrationModel:
    hw = bench if isinstance(bench, StageBench) else StageBench(**bench)
    return get_method("stage", "kinematic").fit(
        columns,
        FitOptions(
            extra={
                "bench": hw,
                "bench_source": bench_source,
                "effects": list(effects),
                "worm_axes": list(worm_axes),
            }
        ),
    )


def _axes_short(model: CalibrationModel, effect: str, axes_named: Sequence[str]) -> list[str]:
    """The stages whose worm the diagnosis saw but the refit cannot determine (one of its pair
    held)."""
    if effect != "periodic_error":
        return []
    short = []
    for ax in axes_named:
        for lab in (f"{ax}_sin_deg", f"{ax}_cos_deg"):
            param = model.parameters.get(f"periodic_error.{lab}")
            if param is None or param.fixed:
                short.append(ax)
                break
    return short


# the chance that a stage without a worm error is taken for one, over both stages (Bonferroni)
WORM_STAGE_ALPHA = 1e-3


def worm_axes_seen(
    labels: Sequence[str],
    values: NDArray[np.float64],
    covariance: NDArray[np.float64],
    alpha: float = WORM_STAGE_ALPHA,
) -> list[str]:
    """The stages whose worm error a diagnosis's fit shows: a stage's sine and cosine terms together
    (chi-square on their covariance, one degree of freedom per term the points determine) beyond
    chance at `alpha` over the stages; else the stage with the clearest terms. A stage whose terms
    the points hardly separate from the rest of the model (a grid step near a whole number of worm
    turns samples a short arc of the worm) has a large covariance there, and a term taken on one
    look at it would fit the model's other errors into a sinusoid that levelling then extrapolates;
    its sine and cosine judged together, at a level for both stages, keep that to `alpha`. A stage
    the points sample at two phases may keep one term that shows nothing: the error is not there,
    and the refit holding that stage's pair at zero loses nothing."""
    by_stage: dict[str, list[int]] = {}
    for i, lab in enumerate(labels):
        by_stage.setdefault(lab[:1], []).append(i)
    score: dict[str, float] = {}
    for stage, rows in by_stage.items():
        variances = np.diag(covariance)[rows]
        picked = [row for row, var in zip(rows, variances) if np.isfinite(var) and var > 0]
        if not picked:
            continue
        value = values[picked]
        chi2 = float(value @ np.linalg.pinv(covariance[np.ix_(picked, picked)]) @ value)
        # how far beyond chance: the chi-square's tail probability, small where clear
        score[stage] = -float(stats.chi2.logsf(chi2, len(picked)))
    level = -np.log(alpha / max(len(by_stage), 1))
    seen = [ax for ax in ("x", "y") if score.get(ax, 0.0) > level]
    if not seen and score:
        seen = [max(score, key=lambda ax: score[ax])]
    return seen


def seen_labels_of(steps: Sequence[Step]) -> dict[str, list[str]]:
    """Per effect a diagnosis named (its workflow's steps), the parameters that carry it: a worm's
    periodic error only on the stages its fit shows it on."""
    seen: dict[str, list[str]] = {}
    for step in steps:
        labels = list(step.after.block(step.effect).labels)
        if step.effect == "periodic_error":
            sl = step.after.block_slice(step.effect)
            axes = worm_axes_seen(labels, step.after.values[sl], step.after.covariance[sl, sl])
            labels = [lab for lab in labels if lab[:1] in axes]
        seen[step.effect] = labels
    return seen


def worm_axes_of(verdicts: Sequence[AdoptionVerdict]) -> list[str]:
    """The stages a stored adoption verdict fits a worm's error on (both for a verdict that does not
    say)."""
    for verdict in verdicts:
        # a verdict stored before the stages were kept has no `axes`
        if verdict.get("effect") == "periodic_error" and (axes := verdict.get("axes")):
            return [str(axis) for axis in axes]
    return ["x", "y"]


def adoption(
    columns: Mapping[str, NDArray[np.float64]],
    named: Sequence[str],
    sensor: str,
    bench: BenchGiven | None,
    bench_source: str,
    have: set[str] | frozenset[str] = frozenset(),
    seen_labels: Mapping[str, Sequence[str]] | None = None,
    keep: Sequence[str] = (),
    worm_axes: Sequence[str] = (),
) -> list[Adoption]:
    """Per named effect: can the record adopt it from these points? Decided by the refit that
    adopting makes (alone, then together with the others that pass), so adopting never fails after
    the diagnosis said yes.

    `seen_labels` are the parameters the diagnosis fitted per effect: a worm's periodic error seen
    on a stage needs both its sine and its cosine determined there (its amplitude and phase), not
    one of them; it is fitted on those stages (and on `worm_axes`, those the record fits already),
    the others held at zero."""
    out: list[Adoption] = []
    candidates: list[str] = []
    for effect in dict.fromkeys(named):
        refusal = _refusal_without_refit(effect, sensor, bench, have)
        if refusal is None:
            candidates.append(effect)
        else:
            out.append(Adoption(effect, False, refusal))
    if not candidates:
        return out
    assert bench is not None
    seen_worm = _worm_stages_seen(seen_labels)
    axes = sorted(set(seen_worm) | set(worm_axes)) or ["x", "y"]
    verdicts = {
        effect: _one(
            columns,
            effect,
            bench,
            bench_source,
            seen_worm if effect == "periodic_error" else (),
            keep,
            axes,
        )
        for effect in candidates
    }
    _check_together(columns, verdicts, keep, bench, bench_source, axes)
    out += [verdicts[effect] for effect in candidates]
    return out


def _refusal_without_refit(
    effect: str,
    sensor: str,
    bench: BenchGiven | None,
    have: set[str] | frozenset[str],
) -> str | None:
    """Why an effect cannot be adopted whatever the points say (None: only a refit can tell)."""
    if effect in IN_CHAIN:
        return "the kinematic calibration models it already (the stacked-stage geometry)"
    if effect in have:
        return "the record fits it already"
    if effect not in EXTRA_EFFECTS:
        return f"not a term the kinematic calibration can take ({', '.join(EXTRA_EFFECTS)})"
    if sensor != "ref" and effect in REFERENCE_EFFECTS:
        return (
            "the measurement sensor's own term: the kinematic record corrects that "
            "sensor by its mounting (zeros, scales, yaw, non-orthogonality, seat tilt), "
            "of which this is none; diagnose with sensor 'ref' for the reference's and "
            "the bench's effects"
        )
    if bench is None:
        return "the record does not state the bench it was calibrated on"
    return None


def _worm_stages_seen(seen_labels: Mapping[str, Sequence[str]] | None) -> list[str]:
    """The stages the diagnosis fitted a worm's periodic error on, from its parameter labels."""
    return sorted(
        {lab[:1] for lab in (seen_labels or {}).get("periodic_error", ()) if lab[:1] in "xy"}
    )


def _check_together(
    columns: Mapping[str, NDArray[np.float64]],
    verdicts: dict[str, Adoption],
    keep: Sequence[str],
    bench: BenchGiven,
    bench_source: str,
    axes: Sequence[str],
) -> None:
    """Effects each adoptable alone may not separate from one another: refit them together and
    turn the verdict of any the joint refit leaves undetermined (in `verdicts`)."""
    ok = [effect for effect, verdict in verdicts.items() if verdict.adoptable]
    if len(ok) <= 1:
        return
    left = _left_undetermined(columns, ok, keep, bench, bench_source, axes)
    for effect, why in left.items():
        if effect not in ok:
            continue
        verdicts[effect] = Adoption(
            effect,
            False,
            f"not separable from the other named effects on these points ({why})",
            MEASUREMENTS.get(effect),
            verdicts[effect].axes,
        )


def _left_undetermined(
    columns: Mapping[str, NDArray[np.float64]],
    ok: list[str],
    keep: Sequence[str],
    bench: BenchGiven,
    bench_source: str,
    axes: Sequence[str],
) -> Mapping[str, str]:
    """The effects the joint refit leaves undetermined, with the reason (every one of them when
    the joint refit itself fails)."""
    try:
        joint = _fit(columns, [k for k in keep if k not in ok] + ok, bench, bench_source, axes)
        left: Mapping[str, str] = joint.fit.get("undetermined_effects") or {}
    except (DegenerateDataError, FitError, InputError, np.linalg.LinAlgError) as exc:
        left = {effect: str(exc) for effect in ok}
    return left


def _one(
    columns: Mapping[str, NDArray[np.float64]],
    effect: str,
    bench: BenchGiven,
    bench_source: str,
    seen_axes: Sequence[str],
    keep: Sequence[str],
    axes: Sequence[str],
) -> Adoption:
    """One effect's verdict from the refit that adds it alone (to the effects the record keeps)."""
    worm = list(axes) if effect == "periodic_error" else None
    try:
        model = _fit(
            columns, [k for k in keep if k != effect] + [effect], bench, bench_source, axes
        )
    except (DegenerateDataError, FitError, InputError, np.linalg.LinAlgError) as exc:
        return Adoption(
            effect,
            False,
            f"the refit with it fails on these points: {exc}",
            MEASUREMENTS.get(effect),
            worm,
        )
    reason = _why_undetermined(model, effect, seen_axes)
    if reason is not None:
        return Adoption(effect, False, reason, MEASUREMENTS.get(effect), worm)
    return Adoption(effect, True, _determined_sentence(model, effect), None, worm)


def _why_undetermined(model: CalibrationModel, effect: str, seen_axes: Sequence[str]) -> str | None:
    """Why the refit that adds the effect does not determine it: none of its parameters, or not
    both terms of a worm seen on a stage (None when it is determined)."""
    undetermined = (model.fit.get("undetermined_effects") or {}).get(effect)
    if undetermined:
        return f"these points determine none of its parameters ({undetermined})"
    short = _axes_short(model, effect, seen_axes)
    if short:
        notes = [
            model.parameters[f"periodic_error.{ax}_sin_deg"].note
            or model.parameters[f"periodic_error.{ax}_cos_deg"].note
            for ax in short
        ]
        return (
            f"seen on the {' and '.join(short)} stage, whose worm error's amplitude and "
            f"phase these points do not determine ({'; '.join(n for n in notes if n)})"
        )
    return None


def _determined_sentence(model: CalibrationModel, effect: str) -> str:
    """What the refit determines of an adoptable effect, and what it holds at zero."""
    free = [
        n for n, param in model.parameters.items() if n.startswith(f"{effect}.") and not param.fixed
    ]
    held = [
        n for n, param in model.parameters.items() if n.startswith(f"{effect}.") and param.fixed
    ]
    return f"the refit determines {', '.join(free)}" + (
        f" (and holds {', '.join(held)} at zero, with the reason in the model's notes)"
        if held
        else ""
    )
