"""Stage motion: move to raw stage angles, level the table in closed loop, stop everything."""

from __future__ import annotations

from collections.abc import Mapping

from fastapi import APIRouter

from service.api.auth import Operator
from service.api.deps import AuditRepoDep, BenchesDep, JobsDep, find_bench
from service.api.models.problem import WRITE, problem_responses
from service.api.models.stage import Level, Levelled, Move, Moved, Stop, Stopped
from service.api.offloop import in_thread
from service.api.problems import ProblemError
from service.bench.runtime import BenchHold, BenchRuntime, Hold
from service.errors import InputError
from service.jobs import level as levelling
from service.storage.store import AuditRepo

router = APIRouter(prefix="/stage", tags=["stage"])


async def _audit(
    audit: AuditRepo, actor: str, action: str, bench: str, details: Mapping[str, object]
) -> None:
    """The audit event of a stage action, written in the worker thread pool: a write waiting for the
    database's write lock (a job storing its points) must not hold up the event loop, which serves
    /tilt and keeps the instruments' streams read."""
    await in_thread(audit.action, actor, action, "bench", bench, details)


def _stage_bench(benches: dict[str, BenchRuntime], name: str | None) -> BenchRuntime:
    bench = find_bench(benches, name)
    if bench.kind != "stage":
        raise ProblemError(
            422,
            "Not a stage bench",
            f"bench: {bench.name!r} is a {bench.kind} bench",
            field="bench",
        )
    return bench


@router.post("/move", response_model=Moved, responses=problem_responses(*WRITE, 404, 409, 503))
async def move(body: Move, benches: BenchesDep, audit: AuditRepoDep, who: Operator) -> Moved:
    """Move both stages to raw stage angles and answer once they stand (409 while a job holds the
    bench)."""
    bench = _stage_bench(benches, body.bench)
    travel = bench.config.stage_bench().travel_deg
    for axis in ("x_deg", "y_deg"):
        if abs(getattr(body, axis)) > travel:
            raise ProblemError(
                422,
                "Outside travel",
                f"{axis}: {getattr(body, axis):g} deg is "
                f"outside the stage travel of ±{travel:g} deg",
                field=axis,
            )
    async with bench.hold(BenchHold(Hold.STAGE_MOVE)):
        x, y = await bench.move_stage(body.x_deg, body.y_deg)
    await _audit(audit, who.name, "stage.move", bench.name, body.model_dump())
    return Moved.model_validate({"stage": {"x_deg": x, "y_deg": y, "moving": False}})


@router.post("/level", response_model=Levelled, responses=problem_responses(*WRITE, 404, 409, 503))
async def level(
    body: Level, benches: BenchesDep, jobs: JobsDep, audit: AuditRepoDep, who: Operator
) -> Levelled:
    """Level the table to a wanted tilt in closed loop (422 out of reach, 409 while a job holds the
    bench)."""
    bench = _stage_bench(benches, body.bench)
    active = jobs.active.get(bench.name)
    if active is None:
        why = jobs.inactive_notes.get(bench.name)
        raise ProblemError(
            409,
            "No active calibration",
            f"bench {bench.name!r} has no active record to level with"
            " (POST /records/{id}/activate)" + (f"; {why}" if why else ""),
        )
    try:
        levelling.commands(active, body.x_deg, body.y_deg)
    except InputError as exc:
        raise ProblemError(
            422, "Target out of reach", f"x_deg, y_deg: {exc}", field="x_deg"
        ) from None
    bench.require("stage")
    bench.require("reference_sensor")
    async with bench.hold(BenchHold(Hold.LEVELLING)):
        out = await levelling.level(
            bench, active, body.x_deg, body.y_deg, body.tolerance_deg, body.max_iterations
        )
    await _audit(
        audit,
        who.name,
        "stage.level",
        bench.name,
        {**body.model_dump(), "within_tolerance": out["within_tolerance"]},
    )
    return Levelled.model_validate(out)


@router.post("/stop", response_model=Stopped, responses=problem_responses(*WRITE, 404))
async def stop(
    benches: BenchesDep, jobs: JobsDep, audit: AuditRepoDep, who: Operator, body: Stop | None = None
) -> Stopped:
    """Stop all motion at once, whatever holds the bench; a running job fails with the reason."""
    bench = find_bench(benches, body.bench if body else None)
    failed = await jobs.stop_bench(bench, who)
    await _audit(audit, who.name, "stage.stop", bench.name, {"failed_job": failed})
    return Stopped(stopped=True, failed_job=failed)
