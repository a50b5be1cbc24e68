"""Bodies of the diagnosis routes: the model-discrepancy workflow on a stored record."""

from __future__ import annotations

import datetime as dt
from typing import Any, Literal

from pydantic import Field

from service.api.models.base import Answer
from service.jobs.requests import RequestBody


class DiagnoseRequest(RequestBody):
    """Which sensor's readings to explain, and the model the search starts from."""

    sensor: Literal["ref", "meas"] = "ref"
    baseline: Literal["kinematic", "linear"] = "kinematic"


class Gap(Answer):
    rms: float | None = None
    max: float | None = None


class DiagnosisBody(Answer):
    id: int
    record_id: int
    sensor: str
    baseline: str
    state: Literal["queued", "running", "succeeded", "failed"]
    phase: str | None = Field(None, description="while running: loading, analysing or storing")
    created_utc: dt.datetime
    created_by: str
    started_utc: dt.datetime | None
    finished_utc: dt.datetime | None
    named_effects: list[str]
    effects: list[Any]
    gap_before_deg: Gap | None = Field(description="residual between model and points before the named effects")
    gap_after_deg: Gap | None = Field(description="the same after them")
    noise_deg: float | None
    noise_source: str | None = None
    steps: list[Any]
    untestable: list[Any]
    conclusion: str | None = None
    error: str | None


class Diagnoses(Answer):
    diagnoses: list[DiagnosisBody]
