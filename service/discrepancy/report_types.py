"""The JSON shapes of the discrepancy report (docs/datasets.md, `discrepancy`) and of its parts.

TypedDicts: the report is built from dict literals and written as JSON, so these are the very
objects the workflow makes, with their keys named for mypy. Nothing here runs.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NotRequired, TypedDict, final

# What `report.clean` makes of anything: JSON values (the report page and the files take these);
# the one JSON alias of the service, kept in service/io.
from service.io.json_value import JSONValue as JSONValue


class EffectReason(TypedDict):
    """An effect and why it is listed: skipped, already in the model, or not measurable here."""

    effect: str
    reason: str


class SignificanceJSON(TypedDict):
    """The extra-sum-of-squares test of one added term (`stats.Significance.as_dict`)."""

    delta_rss_weighted: float
    df_added: int
    f_stat: float
    df_denominator: float | None  # null when the noise level is taken as known (chi-square)
    test: str  # "chi2" or "F"
    p_value: float
    alpha: float
    bic_before: float
    bic_after: float
    delta_bic: float
    denominator: str
    significant: bool


class GoodnessOfFit(TypedDict):
    """Whether the final residual is consistent with the noise level (`stats.goodness_of_fit`)."""

    reduced_chi2: float | None
    dof: int
    p_value: float | None


class StructureDetail(TypedDict, total=False):
    """The figures behind one residual-structure test, each test with its own."""

    strongest_term: str | None  # shape test: the single term explaining most
    strongest_term_span: float
    jump: float  # direction test, in the data's unit
    slope: float  # correlation test
    slope_unit: str
    runs: int  # runs test
    expected: float
    amplitude: float  # worm-period test, in the data's unit
    period_deg: float


class StructureTestJSON(TypedDict):
    """One residual-structure test as the report lists it (`stats.StructureTest.as_dict`)."""

    axis: str
    covariate: str
    test: str
    statistic: float
    p_value: float
    significant: bool
    sentence: str
    detail: NotRequired[StructureDetail]  # only when the test has figures


class ValueWithUnit(TypedDict):
    """A number in its unit."""

    value: float
    unit: str


class MagnitudeEntry(ValueWithUnit):
    """One fitted parameter of an effect in its own unit, with its standard uncertainty."""

    uncertainty: float
    what: NotRequired[str]  # what the parameter means, when its name does not say


# The fitted size of an effect: per parameter name its entry (the scale's polynomial also states
# its `degree`, a plain number). Empty when the size cannot be stated.
Magnitude = Mapping[str, MagnitudeEntry | int]


class CandidateTried(SignificanceJSON):
    """A candidate one selection step added, refitted and tested."""

    effect: str
    rms_after: list[float]  # per axis, in the data's unit
    magnitude: Magnitude


class CandidatePreviewed(SignificanceJSON):
    """A candidate the one-step preview ruled out (approximate figures; no nonlinear refit)."""

    effect: str
    approximate: bool  # always true
    rms_after: list[float]
    magnitude: Magnitude


@final  # its two keys only: a check for the figures tells it from the others
class CandidateFailed(TypedDict):
    """A candidate whose refit failed, with the reason."""

    effect: str
    error: str


CandidateScore = CandidateTried | CandidatePreviewed | CandidateFailed


class StepEvidence(SignificanceJSON):
    """The test that named a step's effect, and what the residual showed before and after."""

    rss_reduction_pct: float
    candidates: list[CandidateScore]
    where_before: list[str]
    structure_before: list[StructureTestJSON]
    structure_after: list[StructureTestJSON]


class StepReport(TypedDict):
    """One named effect: its size, and the evidence that named it."""

    effect: str
    rms_before: list[float]  # per axis, in the data's unit
    rms_after: list[float]
    magnitude: Magnitude
    summary: str
    evidence: StepEvidence


class FinalVsNoise(GoodnessOfFit):
    """The final residual against the noise level."""

    rms_over_noise: list[float | None]  # per axis; null where the noise level is zero
    sentence: str


class Stop(TypedDict):
    """Why the selection ended, and the last step's candidates (none significant)."""

    reason: str
    candidates: list[CandidateScore]


class ReportInputs(TypedDict, total=False):
    """What the caller says of the data, written near the top of the report."""

    sensor: str  # stage data: the sensor whose readings are explained
    n_rows: int
    input: str  # the dataset, or the diagnosis in words


class KinematicBaseline(TypedDict):
    """What the kinematic baseline decided from the data."""

    meas_flip: str
    temp_ref_c: float
    free_geometry: list[str]  # "effect.parameter"


class BaselineLine(TypedDict):
    """The scale baseline's straight line in the lab's terms."""

    arcsec_per_count: MagnitudeEntry
    arcsec_at_zero_count: ValueWithUnit


class ReportExtra(TypedDict, total=False):
    """What a data kind (and then the caller) adds at the end of the report."""

    # per remaining candidate, per parameter: the fraction of its signature the final model leaves
    # visible
    separability: dict[str, dict[str, float]]
    where_largest: list[str]  # stage: the largest residuals of the baseline
    bench: dict[str, float | str]  # stage: `StageBench.record`
    kinematic: KinematicBaseline  # stage, kinematic baseline
    baseline_fit: BaselineLine  # scale
    supported_degree: int  # scale
    supported_model: str  # scale: "poly<degree>"
    # `service.io.provenance.provenance`'s record, added last by the command or the daemon
    provenance: Mapping[str, object]


class DiscrepancyReport(ReportInputs, ReportExtra):
    """The JSON report of `tiltlab discrepancy` and of a diagnosis, in its key order."""

    format_version: int
    kind: str
    baseline: str
    unit: str
    axes: list[str]
    named_effects: list[str]
    chain: list[str]
    steps: list[StepReport]
    skipped: list[EffectReason]
    already_in_model: list[EffectReason]
    notes: list[str]
    noise_level: list[float]  # per axis, in the data's unit
    noise_source: str
    noise_detail: str
    noise_dof: float | None  # null for a specification (known exactly)
    baseline_rms: list[float]
    final_rms: list[float]
    final_vs_noise: FinalVsNoise
    where: list[str]
    where_final: list[str]
    structure_final: list[StructureTestJSON]
    stop: Stop
    alpha: float
    conclusion: str
