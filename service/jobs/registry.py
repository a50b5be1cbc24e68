"""The procedures this daemon runs, by the name a request gives (`procedure`).

A new procedure is a module of its own with one object satisfying `Procedure`
(`service.jobs.procedure`), added here with `register`.
"""

from __future__ import annotations

from service.jobs.angles import ROTATION, SCALE, TURNTABLE
from service.jobs.diagnosis_measurement import DIAGNOSIS_MEASUREMENT
from service.jobs.job_parameters import JobParameters
from service.jobs.procedure import Procedure
from service.jobs.stage_grid import STAGE_GRID

PROCEDURES: dict[str, Procedure] = {}


def register(procedure: Procedure) -> Procedure:
    PROCEDURES[procedure.name] = procedure
    return procedure


for _procedure in (STAGE_GRID, SCALE, ROTATION, TURNTABLE):
    register(_procedure)
# Started by a diagnosis (POST /records/{id}/diagnose with measure: true), never by a request of its
# own: not among the procedures POST /calibrations names.
INTERNAL: dict[str, Procedure] = {DIAGNOSIS_MEASUREMENT.name: DIAGNOSIS_MEASUREMENT}


def procedure_named(name: str) -> Procedure | None:
    return PROCEDURES.get(name)


def procedure_of(parameters: JobParameters | None) -> Procedure:
    """The procedure a stored job ran (jobs stored before procedures had names were stage grids); a
    job a diagnosis started names its procedure beside its request."""
    name = (
        (parameters or {}).get("procedure")
        or (parameters or {}).get("request", {}).get("procedure")
        or STAGE_GRID.name
    )
    procedure = PROCEDURES.get(name) or INTERNAL.get(name)
    if procedure is None:
        raise KeyError(f"no procedure {name!r} in this daemon version")
    return procedure


def names() -> str:
    """The procedures' names as a sentence lists them: "stage-grid, scale, rotation and
    turntable"."""
    *first, last = PROCEDURES
    return f"{', '.join(first)} and {last}" if first else last
