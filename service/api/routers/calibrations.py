"""Calibration jobs: start (202 + Location, Idempotency-Key), read, list, cancel, resume."""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Query, Response
from pydantic import BeforeValidator

from service.api.auth import Operator, Reader
from service.api.deps import (
    BenchesDep,
    DevicesRepoDep,
    JobId,
    JobsDep,
    JobsIfAnyDep,
    JobsRepoDep,
    RecordsRepoDep,
    SettingsDep,
    find_bench,
)
from service.api.models.calibrations import Job, JobList, JobState
from service.api.models.paging import CURSOR, DEFAULT_PAGE, LIMIT, MAX_PAGE, json_answer, rfc3339
from service.api.models.problem import READ, WRITE, problem_responses
from service.api.offloop import in_thread, off_loop
from service.api.problems import ProblemError
from service.bench.runtime import BenchRuntime
from service.jobs.requests import DB_ID_MAX, CalibrationRequest
from service.storage.models import CalibrationJob, CalibrationRecord

router = APIRouter(prefix="/calibrations", tags=["calibrations"])


def job_body(
    job: CalibrationJob, record: CalibrationRecord | None, benches: Mapping[str, BenchRuntime]
) -> Job:
    """A job as the routes and the job stream show it, from the job and the record it made."""
    params = job.parameters or {}
    req = params.get("request", {})
    bench = next(
        (runtime.name for runtime in benches.values() if runtime.bench_id == job.bench_id), None
    )
    validation = record.validation if record else None
    return Job.model_validate(
        {
            "id": job.id,
            "bench": bench or req.get("bench"),
            "procedure": params.get("procedure") or req.get("procedure"),
            "method": job.method,
            "state": job.state,
            "interrupted": job.interrupted,
            "progress": {
                "points_done": job.points_done,
                "points_total": job.points_total,
                "phase": job.phase,
            },
            "created_utc": job.created_at,
            "started_utc": job.started_at,
            "finished_utc": job.finished_at,
            "updated_utc": job.updated_at,
            "created_by": job.created_by,
            "error": job.failure_reason,
            "record": {"id": record.id, "version": record.version} if record else None,
            "validation": None
            if not validation
            else {
                "rms_deg": validation.get("rms_deg"),
                "max_deg": validation.get("max_deg"),
                "n_points": validation.get("n_points"),
                "predicted_expanded_uncertainty_deg": validation.get(
                    "predicted_expanded_uncertainty_deg"
                ),
                "target_expanded_uncertainty_deg": validation.get(
                    "target_expanded_uncertainty_deg"
                ),
            },
            "bench_seconds": job.bench_seconds,
            "request": req,
        }
    )


class JobBodies:
    """Jobs as the routes show them, with the records they made (blocking: from async code in a
    thread)."""

    def __init__(
        self,
        stored_jobs: JobsRepoDep,
        records: RecordsRepoDep,
        benches: BenchesDep,
        manager: JobsIfAnyDep,
    ) -> None:
        self.stored_jobs, self.records, self.benches, self.manager = (
            stored_jobs,
            records,
            benches,
            manager,
        )

    def __call__(self, jobs: Sequence[CalibrationJob]) -> list[Job]:
        """Several jobs with their records read in one query (each as the daemon knows it: an end it
        could not store yet, the disk being full, is shown)."""
        records = self.records.records_of_jobs([j.id for j in jobs])
        known = [self.manager.as_known(j) for j in jobs] if self.manager is not None else list(jobs)
        return [job_body(j, records.get(j.id), self.benches) for j in known]

    def read(self, job_id: int) -> Job:
        """The job as stored now."""
        return self([self.stored_jobs.get_job(job_id)])[0]


JobBodiesDep = Annotated[JobBodies, Depends()]


def _grid_size(body: CalibrationRequest, max_points: int) -> None:
    if body.grid is not None and body.grid.size() > max_points:
        raise ProblemError(
            422,
            "Grid too large",
            f"grid: {body.grid.size()} points; at most {max_points} are taken"
            " (TILTLAB_MAX_GRID_POINTS)",
            field="grid",
        )


@router.post(
    "",
    status_code=202,
    response_model=Job,
    responses={
        200: {
            "model": Job,
            "description": "A repeat of an earlier request's Idempotency-Key: that request's job",
        },
        **problem_responses(*WRITE, 404, 409, 503),
    },
)
async def start(
    body: CalibrationRequest,
    response: Response,
    benches: BenchesDep,
    jobs: JobsDep,
    bodies: JobBodiesDep,
    settings: SettingsDep,
    who: Operator,
    idempotency_key: Annotated[str | None, Header(max_length=200)] = None,
) -> Job:
    """Start a calibration job: 202 with the job and its Location. A repeated Idempotency-Key
    returns that job (200); the same key with another body is 422; a busy bench is 409; a bad grid
    is 422 and starts nothing."""
    _grid_size(body, settings.max_grid_points)
    bench = find_bench(benches, body.bench)
    job, created = await jobs.submit(body, bench, who, idempotency_key)
    response.headers["Location"] = f"/calibrations/{job.id}"
    if not created:
        response.status_code = 200
    return await in_thread(bodies.read, job.id)


@router.get("", response_model=JobList, responses=problem_responses(*READ, 404))
@off_loop
def list_jobs(
    benches: BenchesDep,
    devices: DevicesRepoDep,
    stored_jobs: JobsRepoDep,
    bodies: JobBodiesDep,
    _: Reader,
    state: JobState | None = None,
    bench: Annotated[str | None, Query(max_length=100)] = None,
    updated_since: Annotated[
        dt.datetime | None,
        BeforeValidator(rfc3339),
        Query(
            description="jobs changed at or after this time (RFC 3339, with a zone:"
            " 2026-03-01T12:00:00Z)"
        ),
    ] = None,
    cursor: Annotated[int | None, Query(ge=1, le=DB_ID_MAX, description=CURSOR)] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE, description=LIMIT)] = DEFAULT_PAGE,
) -> Response:
    """Jobs newest first, filtered by state, bench and last change; `next_cursor` pages on."""
    bench_id = None
    # a bench of this daemon, or of another daemon of the lab (the database knows it)
    if bench is not None:
        bench_id = benches[bench].bench_id if bench in benches else devices.bench_id_of(bench)
        if bench_id is None:
            find_bench(benches, bench)  # the 404 naming the benches there are
    if updated_since is not None and updated_since.tzinfo is None:
        raise ProblemError(
            422,
            "Invalid request",
            "updated_since: give a time zone (e.g. Z)",
            field="updated_since",
        )
    found = stored_jobs.list_jobs(
        state=state, bench_id=bench_id, updated_since=updated_since, before_id=cursor, limit=limit
    )
    return json_answer(
        JobList(jobs=bodies(found), next_cursor=found[-1].id if len(found) == limit else None)
    )


@router.get("/{job_id}", response_model=Job, responses=problem_responses(*READ, 404))
@off_loop
def read(job_id: JobId, bodies: JobBodiesDep, _: Reader) -> Job:
    return bodies.read(job_id)


@router.post("/{job_id}/cancel", response_model=Job, responses=problem_responses(*WRITE, 404, 409))
async def cancel(job_id: JobId, jobs: JobsDep, bodies: JobBodiesDep, who: Operator) -> Job:
    """Stop a queued or running job; what it measured is kept."""
    job = await jobs.cancel(job_id, who)
    return (await in_thread(bodies, [job]))[0]


@router.post(
    "/{job_id}/resume",
    status_code=202,
    response_model=Job,
    responses=problem_responses(*WRITE, 404, 409),
)
async def resume(
    job_id: JobId, response: Response, jobs: JobsDep, bodies: JobBodiesDep, who: Operator
) -> Job:
    """Continue a job a restart interrupted, from its stored points."""
    job = await jobs.resume(job_id, who)
    response.headers["Location"] = f"/calibrations/{job.id}"
    return await in_thread(bodies.read, job_id)
