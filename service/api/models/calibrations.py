"""Bodies of the calibration job routes (the request is
service.jobs.requests.CalibrationRequest)."""

from __future__ import annotations

import datetime as dt
from typing import Literal

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
    predicted_expanded_uncertainty_deg: float | None = Field(
        None,
        description="adaptive design: the expanded uncertainty of the correction over the range "
        "the job predicted before validating (its target met when this is at most the target)",
    )
    target_expanded_uncertainty_deg: float | None = Field(
        None, description="adaptive design: the target asked for"
    )


class BenchSeconds(Answer):
    """Bench time a job spent, in bench seconds (a simulated bench's speed-up does not change
    it)."""

    total: float = Field(description="moving + settling + reading")
    moving: float = Field(description="stage moves (approach and final) of every point")
    settling: float = Field(description="from the stage standing to the readings settled")
    reading: float = Field(description="from settled to a point's last reading")


class Job(Answer):
    id: int
    bench: str | None
    procedure: str | None
    method: str
    state: JobState
    interrupted: bool = Field(
        description="left unfinished by a previous run of the daemon (resumable)"
    )
    progress: Progress
    created_utc: dt.datetime
    started_utc: dt.datetime | None
    finished_utc: dt.datetime | None
    updated_utc: dt.datetime | None
    created_by: str
    error: str | None
    record: RecordRef | None = Field(description="the record the job made, once it has")
    validation: ValidationSummary | None
    bench_seconds: BenchSeconds | None = Field(
        None, description="bench time spent so far (null for jobs run before it was counted)"
    )
    request: dict[str, object] = Field(description="the request the job was started with")


class JobList(Answer):
    jobs: list[Job]
    next_cursor: int | None = Field(
        description="give as `cursor` for the next page; null on the last"
    )
