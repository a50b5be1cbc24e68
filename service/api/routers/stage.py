"""Stage motion: raw moves, closed-loop levelling from the active record, and stop."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Request
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from service.api.auth import Operator
from service.api.deps import find_bench
from service.api.problems import ProblemError
from service.bench.runtime import BenchHold, Hold
from service.errors import InputError
from service.jobs import level as levelling

router = APIRouter(prefix="/stage", tags=["stage"])


class Move(BaseModel):
    model_config = ConfigDict(extra="forbid")
    bench: str | None = None
    x_deg: float
    y_deg: float


class Level(BaseModel):
    model_config = ConfigDict(extra="forbid")
    bench: str | None = None
    x_deg: float
    y_deg: float
    tolerance_deg: Annotated[float, Field(gt=0, le=1)] = 0.005
    max_iterations: Annotated[int, Field(ge=1, le=50)] = 5


class Stop(BaseModel):
    model_config = ConfigDict(extra="forbid")
    bench: str | None = None


async def _audit(request: Request, actor: str, action: str, bench: str, details: dict) -> None:
    """The audit event of a stage action, written in the worker thread pool: a write waiting for the
    database's write lock (a job storing its points) must not hold up the event loop, which serves
    /tilt and keeps the instruments' streams read."""
    await run_in_threadpool(request.app.state.store.audit_action, actor, action, "bench", bench, details)


def _stage_bench(request: Request, name: str | None):  # type: ignore[no-untyped-def]
    bench = find_bench(request, name)
    if bench.kind != "stage":
        raise ProblemError(422, "Not a stage bench", f"bench: {bench.name!r} is a {bench.kind} bench", field="bench")
    return bench


@router.post("/move")
async def move(body: Move, request: Request, who: Operator) -> dict:
    """Move both stages to raw stage angles and answer once they stand (409 while a job holds the bench)."""
    bench = _stage_bench(request, body.bench)
    travel = bench.config.stage_bench().travel_deg
    for f in ("x_deg", "y_deg"):
        if abs(getattr(body, f)) > travel:
            raise ProblemError(422, "Outside travel", f"{f}: {getattr(body, f):g} deg is outside the stage travel"
                               f" of ±{travel:g} deg", field=f)
    async with bench.hold(BenchHold(Hold.STAGE_MOVE)):
        x, y = await bench.move_stage(body.x_deg, body.y_deg)
    await _audit(request, who.name, "stage.move", bench.name, body.model_dump())
    return {"stage": {"x_deg": x, "y_deg": y, "moving": False}}


@router.post("/level")
async def level(body: Level, request: Request, who: Operator) -> dict:
    """Level the table to a wanted tilt in closed loop (422 out of reach, 409 while a job holds the bench)."""
    bench = _stage_bench(request, body.bench)
    active = request.app.state.jobs.active.get(bench.name)
    if active is None:
        why = request.app.state.jobs.inactive_notes.get(bench.name)
        raise ProblemError(409, "No active calibration", f"bench {bench.name!r} has no active record to level with"
                           " (POST /records/{id}/activate)" + (f"; {why}" if why else ""))
    try:
        levelling.commands(active, body.x_deg, body.y_deg)
    except InputError as exc:
        raise ProblemError(422, "Target out of reach", f"x_deg, y_deg: {exc}", field="x_deg") from None
    bench.require("stage")
    bench.require("reference_sensor")
    async with bench.hold(BenchHold(Hold.LEVELLING)):
        out = await levelling.level(bench, active, body.x_deg, body.y_deg, body.tolerance_deg, body.max_iterations)
    await _audit(request, who.name, "stage.level", bench.name,
                 {**body.model_dump(), "within_tolerance": out["within_tolerance"]})
    return out


@router.post("/stop")
async def stop(request: Request, who: Operator, body: Stop | None = None) -> dict:
    """Stop all motion at once, whatever holds the bench; a running job fails with the reason."""
    bench = find_bench(request, body.bench if body else None)
    failed = await request.app.state.jobs.stop_bench(bench, who)
    await _audit(request, who.name, "stage.stop", bench.name, {"failed_job": failed})
    return {"stopped": True, "failed_job": failed}
