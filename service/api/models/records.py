"""Bodies of the calibration record routes."""

from __future__ import annotations

import datetime as dt
from typing import Any, Literal

from pydantic import Field

from service.api.models.base import Answer
from service.api.models.calibrations import BenchSeconds

RecordStatus = Literal["draft", "approved", "rejected"]


class CalibratedRange(Answer):
    frame: str = Field(description="the frame of the tilts: reference_sensor")
    x_deg: list[float] = Field(description="[min, max]")
    y_deg: list[float] = Field(description="[min, max]")


class Conformity(Answer):
    """The statements of conformity the specification asks for (the certificate states the same)."""

    x: str | None = Field(description="pass, conditionalPass, conditionalFail or fail")
    y: str | None = Field(description="pass, conditionalPass, conditionalFail or fail")
    decision_rule: str
    max_permissible_error_deg: float
    guard_band_fraction: float | None = None
    parameters: dict[str, str | None] | None = None
    largest_probability_of_false_acceptance: dict[str, float | None] = Field(
        description="per quantity, over its points that pass (null when none passes)"
    )
    worst_point: dict[str, dict[str, object]] = Field(
        description="per quantity, the error and U the statement rests on"
    )


class Record(Answer):
    id: int
    device_id: int
    bench: str | None
    kind: str
    version: int
    method: str
    created_utc: dt.datetime
    operator: str
    job_id: int | None
    active: bool = Field(description="whether /tilt and levelling use this record")
    validation: dict[str, object] | None
    temp_c: float | None
    conditions: dict[str, object] | None
    raw_data: dict[str, object] | None
    supersedes_id: int | None
    content_sha256: str
    reference_standards: list[Any] | None
    status: RecordStatus
    budget: Any = Field(
        None,
        description="the uncertainty budget of the record's results; `traceable` says whether a "
        "reference standard's uncertainty is in it (else `warning`: \"no reference "
        'standard: not traceable", and the record gets no certificate)',
    )
    conformity: Conformity | None = Field(
        None,
        description="where the record's order has a specification: the "
        "statements of conformity (as on the certificate)",
    )
    calibrated_range: CalibratedRange | None = Field(
        None, description="the table tilts a stage record was fitted on"
    )
    bench_seconds: BenchSeconds | None = Field(
        None, description="the bench time its job spent measuring it"
    )


class RecordList(Answer):
    records: list[Record]
    next_cursor: int | None = Field(
        None, description="the `cursor` of the next page; null on the last page"
    )


class Covariance(Answer):
    names: list[str]
    matrix: list[list[float | None]]


class ModelFile(Answer):
    """MODEL.json: the fitted model as `tiltlab correct --model` reads it."""

    format_version: int
    kind: str
    method: str
    columns: list[str]
    parameters: dict[str, dict[str, object]]
    covariance: Covariance | None = None
    residuals: Any = None
    fit: Any = None
    notes: list[str] | None = None
    options: Any = None
    state: Any = None
    provenance: Any = None


class ResidualPoint(Answer):
    point: int
    role: Literal["fit", "validation"]
    stage_x_deg: float
    stage_y_deg: float
    ref_x_deg: float
    ref_y_deg: float
    before_x_deg: float
    before_y_deg: float
    after_x_deg: float
    after_y_deg: float


class Residuals(Answer):
    record_id: int
    method: str
    n_fit: int
    rms_before_deg: float | None
    rms_after_deg: float | None
    points: list[ResidualPoint]
