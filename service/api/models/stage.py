"""Bodies of the stage routes: requests and answers."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from service.api.models.base import Answer
from service.api.models.tilt import AxisPair, StagePose
from service.jobs.requests import Count, Finite, RequestBody, Text

BenchName = Annotated[
    Text, Field(max_length=100, description="the bench; may be left out when the daemon runs one")
]


class Move(RequestBody):
    bench: BenchName | None = None
    x_deg: Finite
    y_deg: Finite


class Level(RequestBody):
    bench: BenchName | None = None
    x_deg: Finite = Field(description="wanted table tilt about x")
    y_deg: Finite = Field(description="wanted table tilt about y")
    tolerance_deg: Annotated[Finite, Field(gt=0, le=1)] = 0.005
    max_iterations: Annotated[Count, Field(ge=1, le=50)] = 5


class Stop(RequestBody):
    bench: BenchName | None = None


class Home(RequestBody):
    bench: BenchName | None = None


class Moved(Answer):
    stage: StagePose


class Levelled(Answer):
    achieved: AxisPair = Field(
        description="the table tilt read back: the reference sensor's settled mean, through the "
        "active record's model of the reference's own errors when it has one"
    )
    reference_raw: AxisPair | None = Field(
        None, description="the reference sensor's settled mean as it came"
    )
    iterations: int
    stage: AxisPair
    within_tolerance: bool
    measured_by: str | None = None


class Homed(Answer):
    homed: bool
    stage: StagePose


class Stopped(Answer):
    stopped: bool
    failed_job: int | None = Field(description="the job the stop failed, if one was running")
