"""Bodies of the calibration job routes (the request is service.jobs.requests.CalibrationRequest)."""

from __future__ import annotations

import datetime as dt
from typing import Any, Literal

from pydantic import Field

from service.api.models.base import Answer

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]


class Progress(Answer):
    points_done: int
    points_total: int
    phase: str | None = Field(description="measuring, fitting or validating")


class RecordRef(Answer):
    id: int
    version: int


class ValidationSummary(Answer):
    rms_deg: float | None
    max_deg: float | None
    n_points: int | None


class Job(Answer):
    id: int
    bench: str | None
    procedure: str | None
    method: str
    state: JobState
    interrupted: bool = Field(description="left unfinished by a previous run of the daemon (resumable)")
    progress: Progress
    created_utc: dt.datetime
    started_utc: dt.datetime | None
    finished_utc: dt.datetime | None
    updated_utc: dt.datetime | None
    created_by: str
    error: str | None
    record: RecordRef | None = Field(description="the record the job made, once it has")
    validation: ValidationSummary | None
    request: dict[str, Any] = Field(description="the request the job was started with")


class JobList(Answer):
    jobs: list[Job]
    next_cursor: int | None = Field(description="give as `cursor` for the next page; null on the last")
