"""Homing the stage: after power-up a controller refuses moves ("not homed") until each axis has
found its reference switch; `POST /stage/home` does that and answers once both axes stand at 0."""

from __future__ import annotations

from fastapi import APIRouter

from service.api.auth import Operator
from service.api.deps import AuditRepoDep, BenchesDep, find_bench
from service.api.models.problem import WRITE, problem_responses
from service.api.models.stage import Home, Homed
from service.api.offloop import in_thread
from service.api.problems import ProblemError
from service.bench.runtime import BenchHold, Hold

router = APIRouter(prefix="/stage", tags=["stage"])


@router.post("/home", response_model=Homed, responses=problem_responses(*WRITE, 404, 409, 503))
async def home(
    benches: BenchesDep, audit: AuditRepoDep, who: Operator, body: Home | None = None
) -> Homed:
    """Home both stage axes and answer once they stand (409 while a job holds the bench)."""
    bench = find_bench(benches, body.bench if body else None)
    if bench.kind != "stage":
        raise ProblemError(
            422,
            "Not a stage bench",
            f"bench: {bench.name!r} is a {bench.kind} bench",
            field="bench",
        )
    async with bench.hold(BenchHold(Hold.HOMING)):
        x, y = await bench.home_stage()
    await in_thread(
        audit.action, who.name, "stage.home", "bench", bench.name, {"bench": bench.name}
    )
    return Homed.model_validate({"homed": True, "stage": {"x_deg": x, "y_deg": y, "moving": False}})
