"""Calibration jobs: start (202 + Location, Idempotency-Key), read, list, cancel, resume."""

from __future__ import annotations

import datetime as dt
from typing import Annotated

from fastapi import APIRouter, Header, Query, Request, Response
from fastapi.concurrency import run_in_threadpool

from service.api.auth import Operator, Reader
from service.api.deps import find_bench
from service.api.problems import ProblemError
from service.jobs.requests import CalibrationRequest
from service.storage.errors import UnknownEntity
from service.storage.models import CalibrationJob, CalibrationRecord

router = APIRouter(prefix="/calibrations", tags=["calibrations"])


def job_json(request: Request, job: CalibrationJob) -> dict:
    store = request.app.state.store
    bench = next((b.name for b in request.app.state.benches.values() if b.bench_id == job.bench_id), None)
    with store.session() as s:
        # the job's own record: the first made from its points (an adopted diagnosis adds later versions)
        rec = s.query(CalibrationRecord).filter(CalibrationRecord.job_id == job.id).order_by(CalibrationRecord.id).first()
    params = job.parameters or {}
    req = params.get("request", {})
    v = rec.validation if rec else None
    return {"id": job.id, "bench": bench or req.get("bench"), "procedure": req.get("procedure"), "method": job.method,
            "state": job.state, "interrupted": job.interrupted,
            "progress": {"points_done": job.points_done, "points_total": job.points_total, "phase": job.phase},
            "created_utc": job.created_at, "started_utc": job.started_at, "finished_utc": job.finished_at,
            "updated_utc": job.updated_at, "created_by": job.created_by, "error": job.failure_reason,
            "record": {"id": rec.id, "version": rec.version} if rec else None,
            "validation": None if not v else {"rms_deg": v.get("rms_deg"), "max_deg": v.get("max_deg"),
                                              "n_points": v.get("n_points")},
            "request": req}


def _job_json_of(request: Request, job_id: int) -> dict:
    """Blocking (database): from async routes through the thread pool."""
    return job_json(request, request.app.state.store.get_job(job_id))


def _job(request: Request, job_id: int) -> CalibrationJob:
    try:
        return request.app.state.store.get_job(job_id)
    except UnknownEntity:
        raise ProblemError(404, "Unknown job", f"id: no calibration job {job_id}", field="id") from None


@router.post("", status_code=202)
async def start(body: CalibrationRequest, request: Request, response: Response, who: Operator,
                idempotency_key: Annotated[str | None, Header(max_length=200)] = None) -> dict:
    """Start a calibration job: 202 with the job and its Location. A repeated Idempotency-Key returns that
    job (200); the same key with another body is 422; a busy bench is 409; a bad grid is 422 and starts nothing."""
    bench = find_bench(request, body.bench)
    job, created = await request.app.state.jobs.submit(body, bench, who, idempotency_key)
    response.headers["Location"] = f"/calibrations/{job.id}"
    if not created:
        response.status_code = 200
    return await run_in_threadpool(_job_json_of, request, job.id)


@router.get("")
def list_jobs(request: Request, _: Reader,
              state: Annotated[str | None, Query(pattern="^(queued|running|succeeded|failed|cancelled)$")] = None,
              bench: str | None = None, updated_since: dt.datetime | None = None,
              cursor: Annotated[int | None, Query(ge=1, description="next_cursor of the previous page")] = None,
              limit: Annotated[int, Query(ge=1, le=500)] = 50) -> dict:
    """Jobs newest first, filtered by state, bench and last change; `next_cursor` pages on."""
    bench_id = find_bench(request, bench).bench_id if bench is not None else None
    if updated_since is not None and updated_since.tzinfo is None:
        raise ProblemError(422, "Invalid request", "updated_since: give a time zone (e.g. Z)", field="updated_since")
    jobs = request.app.state.store.list_jobs(state=state, bench_id=bench_id, updated_since=updated_since,
                                             before_id=cursor, limit=limit)
    return {"jobs": [job_json(request, j) for j in jobs],
            "next_cursor": jobs[-1].id if len(jobs) == limit else None}


@router.get("/{job_id}")
def read(job_id: int, request: Request, _: Reader) -> dict:
    return job_json(request, _job(request, job_id))


@router.post("/{job_id}/cancel")
async def cancel(job_id: int, request: Request, who: Operator) -> dict:
    """Stop a queued or running job; what it measured is kept."""
    await run_in_threadpool(_job, request, job_id)
    job = await request.app.state.jobs.cancel(job_id, who)
    return await run_in_threadpool(job_json, request, job)


@router.post("/{job_id}/resume", status_code=202)
async def resume(job_id: int, request: Request, response: Response, who: Operator) -> dict:
    """Continue a job a restart interrupted, from its stored points."""
    await run_in_threadpool(_job, request, job_id)
    job = await request.app.state.jobs.resume(job_id, who)
    response.headers["Location"] = f"/calibrations/{job.id}"
    return await run_in_threadpool(_job_json_of, request, job_id)
