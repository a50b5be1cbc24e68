"""What a job keeps in its `parameters` (the job's JSON column): the request it was made from, its
points and how they are measured, and what its procedure or the diagnosis that started it adds.

The column is JSON of one of these shapes; `parameters_of` reads a stored job's as such.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, TypedDict, cast

if TYPE_CHECKING:
    from service.discrepancy.design import PlanPartJSON
    from service.discrepancy.report_types import EffectReason
    from service.jobs.requests import CalibrationRequest
    from service.storage.models import CalibrationJob


class GridJSON(TypedDict, total=False):
    """A request's grid (service.jobs.requests.Grid): a rectangle, explicit stage points, or a
    procedure's angles (degrees), the unused forms null."""

    x_deg: list[float] | None
    y_deg: list[float] | None
    n_x: int | None
    n_y: int | None
    points: list[list[float]] | None
    angles_deg: list[float] | None
    range_deg: list[float] | None
    n: int | None


class SettleJSON(TypedDict):
    """How a point is settled: the tolerance (degrees) over a window, and how long to wait (s)."""

    tolerance_deg: float
    window_s: float
    timeout_s: float


class ValidationRequestJSON(TypedDict):
    """How many validation points the request asks for."""

    n_points: int


class AxisReferenceJSON(TypedDict):
    """Turntable: the axis tilt measured independently (arcsec)."""

    north_arcsec: float
    east_arcsec: float


class StatedConditionJSON(TypedDict):
    """An ambient condition the request states: its value and standard uncertainty."""

    value: float
    standard_uncertainty: float


class ConditionsJSON(TypedDict):
    """The laboratory's ambient conditions as the request states them (°C, % relative
    humidity)."""

    ambient_temperature_c: StatedConditionJSON | None
    relative_humidity_pct: StatedConditionJSON | None


class RequestJSON(TypedDict, total=False):
    """A calibration request as its job keeps it: the validated CalibrationRequest's JSON with the
    bench named (a diagnosis's measurement writes the parts it uses)."""

    bench: str | None
    procedure: str
    method: str
    grid: GridJSON | None
    samples_per_point: int
    settle: SettleJSON
    validation: ValidationRequestJSON
    reference_standards: list[int]
    order_id: int | None
    reference: AxisReferenceJSON | None
    conditions: ConditionsJSON | None
    note: str | None
    design: str
    target_expanded_uncertainty_deg: float | None


class AdaptiveAdmission(TypedDict):
    """What an adaptive job keeps of its admission (degrees): the standard uncertainty every
    corrected tilt carries whatever is measured, and that part expanded (k = 2)."""

    fixed_u_deg: float
    floor_fixed_deg: float


class OperatorPerson(TypedDict):
    """Who ran the job, as the token named them when it was submitted (certificates state it)."""

    name: str
    function: str | None


class DiagnosisPlanSummary(TypedDict):
    """What a diagnosis's measurement keeps of the plan it measures: its parts, what the bench
    cannot measure (and why) and the estimated bench seconds."""

    parts: list[PlanPartJSON]
    cannot: list[EffectReason]
    estimated_bench_s: float


# a planned point as stored: an angle (degrees), or a stage point's (x, y) and, for a diagnosis's
# measurement, the side each stage is approached from
StoredPoint = float | Sequence[float]


class JobParameters(TypedDict, total=False):
    """A job's `parameters`: its procedure (named where a diagnosis started it), the request, the
    planned fit and validation points, the outlier rule and approach, the instruments it reads by
    role (device ids), an adaptive job's admission, the operator, and the diagnosis, record and
    plan a diagnosis's measurement was made for."""

    procedure: str
    request: RequestJSON
    fit_points: Sequence[StoredPoint]
    validation_points: Sequence[StoredPoint]
    outlier_rule: str
    approach: str
    device_ids: dict[str, int | None]
    adaptive: AdaptiveAdmission
    operator_person: OperatorPerson
    diagnosis_id: int
    record_id: int
    plan: DiagnosisPlanSummary


def parameters_of(job: CalibrationJob) -> JobParameters:
    """A stored job's parameters (the JSON a job of this daemon wrote as JobParameters)."""
    return cast(JobParameters, job.parameters)


def request_json(req: CalibrationRequest, bench: str) -> RequestJSON:
    """What a job keeps of its request: the validated request's JSON (every field, the defaults
    filled in), with the bench it runs on."""
    body = cast(RequestJSON, req.model_dump(mode="json"))
    body["bench"] = bench
    return body
