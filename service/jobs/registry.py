"""The procedures this daemon runs, by the name a request gives (`procedure`).

A new procedure is a module of its own with one object satisfying `Procedure`
(`service.jobs.procedure`), added here with `register`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from service.jobs.angles import ROTATION, SCALE, TURNTABLE
from service.jobs.procedure import Procedure
from service.jobs.stage_grid import STAGE_GRID

PROCEDURES: dict[str, Procedure] = {}


def register(procedure: Procedure) -> Procedure:
    PROCEDURES[procedure.name] = procedure
    return procedure


for _procedure in (STAGE_GRID, SCALE, ROTATION, TURNTABLE):
    register(_procedure)


def procedure_named(name: str) -> Procedure | None:
    return PROCEDURES.get(name)


def procedure_of(parameters: Mapping[str, Any] | None) -> Procedure:
    """The procedure a stored job ran (jobs stored before procedures had names were stage grids)."""
    name = (parameters or {}).get("request", {}).get("procedure") or STAGE_GRID.name
    procedure = PROCEDURES.get(name)
    if procedure is None:
        raise KeyError(f"no procedure {name!r} in this daemon version")
    return procedure


def names() -> str:
    """The procedures' names as a sentence lists them: "stage-grid, scale, rotation and turntable"."""
    *first, last = PROCEDURES
    return f"{', '.join(first)} and {last}" if first else last
