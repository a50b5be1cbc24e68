"""Bodies of the diagnosis routes: the model-discrepancy workflow on a stored record."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field, Strict, model_validator

from service.api.models.base import Answer
from service.jobs.requests import RequestBody


class DiagnoseRequest(RequestBody):
    """Which sensor's readings to explain, the model the search starts from, and whether to measure
    first what the stored points cannot test."""

    # the document states what the validator below refuses: `measure` and `plan_only` not both true
    model_config = ConfigDict(
        json_schema_extra={
            "not": {
                "required": ["measure", "plan_only"],
                "properties": {"measure": {"const": True}, "plan_only": {"const": True}},
            }
        }
    )

    sensor: Literal["ref", "meas"] = "ref"
    baseline: Literal["kinematic", "linear"] = "kinematic"
    measure: Annotated[bool, Strict()] = Field(
        False,
        description="plan the shortest measurement that tests what the record's "
        "points cannot (both approach directions, a worm scan finer than its period, poses "
        "measured again later), run it as a job on the record's bench (which must be free: "
        "409), and diagnose the record's points with the new ones",
    )
    plan_only: Annotated[bool, Strict()] = Field(
        False,
        description="answer 200 with that plan (points, approach directions, estimated bench "
        "time) and what the stored points show, moving nothing and storing no diagnosis",
    )

    @model_validator(mode="after")
    def _one(self) -> DiagnoseRequest:
        if self.measure and self.plan_only:
            raise ValueError(
                "measure and plan_only: give one (plan_only shows the plan measure would run)"
            )
        return self


class AdoptRequest(RequestBody):
    """Which of the adoptable named effects to add; all of them when the body or `effects` is left
    out."""

    effects: (
        list[
            Literal[
                "backlash",
                "periodic_error",
                "sensor_nonlinearity",
                "temperature_drift",
                "time_drift",
            ]
        ]
        | None
    ) = Field(
        None,
        min_length=1,
        description="the named effects to add, each one the diagnosis named and found "
        "adoptable (409 otherwise); a second effect of weaker evidence can be "
        "left out so that it does not take part of the calibration's geometry",
    )


class Gap(Answer):
    rms: float | None = None
    max: float | None = None


class Adoption(Answer):
    effect: str
    adoptable: bool
    reason: str
    measurement: str | None = None


class DiagnosisPlan(Answer):
    """What a record's stored points show and cannot test, and the measurement `measure: true` would
    run."""

    record_id: int
    sensor: str
    baseline: str
    named_effects: list[str]
    gap_before_deg: Gap | None
    gap_after_deg: Gap | None
    noise_deg: float | None
    untestable: list[Any]
    adoptable: bool
    adoption: list[Adoption]
    n_points: int
    plan: dict[str, object] = Field(
        description="points (stage_x_deg, stage_y_deg, dir_x, dir_y: +1 approached from "
        "below, -1 from above), parts (per candidate: why, the measurement, its points), "
        "what cannot be measured on this bench, estimated_bench_s, summary"
    )


class DiagnosisBody(Answer):
    id: int
    record_id: int
    sensor: str
    baseline: str
    state: Literal["queued", "running", "succeeded", "failed"]
    phase: str | None = Field(
        None,
        description="while running: loading, analysing or storing; with measure: true "
        "first planning (the record's points alone) and measuring (the planned job)",
    )
    created_utc: dt.datetime
    created_by: str
    started_utc: dt.datetime | None
    finished_utc: dt.datetime | None
    named_effects: list[str]
    effects: list[Any]
    gap_before_deg: Gap | None = Field(
        description="residual between model and points before the named effects"
    )
    gap_after_deg: Gap | None = Field(description="the same after them")
    noise_deg: float | None
    noise_source: str | None = None
    steps: list[Any]
    untestable: list[Any]
    adoptable: bool | None = Field(
        None,
        description="whether POST /diagnoses/{id}/adopt can add a named effect "
        "(null before the diagnosis ends)",
    )
    adoption: list[Adoption] = Field(
        default_factory=list,
        description="per named effect: whether the record can "
        "adopt it from these points, why not, and the measurement that would tell",
    )
    measurement_plan: dict[str, object] | None = Field(
        None,
        description="the measurement that would test what these "
        "points cannot (what measure: true runs)",
    )
    measurement: dict[str, object] | None = Field(
        None,
        description="with measure: true: the plan, the job that measured "
        "it, and what the record's points alone showed before",
    )
    data: dict[str, object] | None = Field(
        None,
        description="the points diagnosed: the record's, and those of measurements made for it",
    )
    residual_maps: dict[str, object] | None = Field(
        None,
        description="per point diagnosed: stage_deg [x, y], approach [dir_x, dir_y], and the "
        "residual [x, y] (measured - model, deg) with the baseline alone (before_deg) and with "
        "the named effects (after_deg): the maps to draw side by side",
    )
    conclusion: str | None = None
    error: str | None


class Diagnoses(Answer):
    diagnoses: list[DiagnosisBody]
    next_cursor: int | None = Field(
        None, description="the `cursor` of the next page; null on the last page"
    )
