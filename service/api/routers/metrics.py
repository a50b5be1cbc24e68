"""GET /metrics: the daemon's Prometheus exposition (scope read)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from starlette.concurrency import run_in_threadpool

from service.api.auth import Reader
from service.api.deps import StoreDep
from service.api.metrics import MetricsDep
from service.api.models.problem import problem_responses

router = APIRouter(tags=["health"])


@router.get("/metrics", response_class=Response,
            responses={200: {"description": "Prometheus text exposition format 0.0.4",
                             "content": {CONTENT_TYPE_LATEST.split(";")[0]: {"schema": {"type": "string"}}}},
                       **problem_responses(401, 403)})
async def metrics(metrics: MetricsDep, store: StoreDep, _: Reader) -> Response:
    """HTTP requests by route and status with latency histograms, serial counters per device, jobs by
    state, WebSocket clients and dropped messages, and the job writes waiting for the database."""
    counts = await run_in_threadpool(store.job_counts_by_state)
    metrics.sources["job_counts"] = lambda: counts
    body = await run_in_threadpool(generate_latest, metrics.registry)
    return Response(body, media_type=CONTENT_TYPE_LATEST)
