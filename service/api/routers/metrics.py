"""GET /metrics: the daemon's Prometheus exposition (scope read)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from starlette.concurrency import run_in_threadpool

from service.api.auth import Reader
from service.api.deps import DatabaseDep, JobsRepoDep
from service.api.metrics import MetricsDep
from service.api.models.problem import READ, problem_responses
from service.api.offloop import DatabaseSlow, in_thread
from service.storage.outage import unreachable

router = APIRouter(tags=["health"])


@router.get(
    "/metrics",
    response_class=Response,
    responses={
        200: {
            "description": "Prometheus text exposition format 0.0.4",
            "content": {CONTENT_TYPE_LATEST.split(";")[0]: {"schema": {"type": "string"}}},
        },
        **problem_responses(*READ),
    },
)
async def metrics(
    metrics: MetricsDep, stored_jobs: JobsRepoDep, database: DatabaseDep, _: Reader
) -> Response:
    """HTTP requests by route and status with latency histograms, serial counters per device, jobs
    by state (left out while the database is away), WebSocket clients and dropped messages, the job
    writes handed over, and whether the database answers (with the writes and samples waiting for
    it)."""
    try:
        counts = await in_thread(stored_jobs.job_counts_by_state)
    # the database does not answer in time: everything else is still worth scraping
    except DatabaseSlow:
        counts = {}
    except Exception as exc:  # the database away: everything else is still worth scraping
        if not unreachable(exc):
            raise
        database.away(exc)
        counts = {}
    metrics.sources["job_counts"] = lambda: counts
    body = await run_in_threadpool(generate_latest, metrics.registry)
    return Response(body, media_type=CONTENT_TYPE_LATEST)
