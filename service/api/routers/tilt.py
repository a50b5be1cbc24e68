from __future__ import annotations

import datetime as dt

from fastapi import APIRouter
from pydantic import BaseModel

from service.api.deps import BenchDep

router = APIRouter(tags=["tilt"])


class TiltReading(BaseModel):
    time_utc: dt.datetime
    bench: str
    stage_x_deg: float
    stage_y_deg: float
    meas_x_deg: float
    meas_y_deg: float
    ref_x_deg: float
    ref_y_deg: float
    temp_c: float
    tilt_x_deg: float | None
    tilt_y_deg: float | None
    calibration: str | None
    note: str


@router.get("/tilt", response_model=TiltReading)
def tilt(bench: BenchDep) -> TiltReading:
    """The bench's current readings. Corrected table tilt needs an active calibration: until one is
    active the tilt fields are null and the raw sensor readings are given as they are."""
    r = bench.read()
    return TiltReading(time_utc=dt.datetime.now(dt.timezone.utc), bench=bench.name, tilt_x_deg=None, tilt_y_deg=None,
                       calibration=None, note="no active calibration: raw sensor readings only",
                       **{k: r[k] for k in ("stage_x_deg", "stage_y_deg", "meas_x_deg", "meas_y_deg", "ref_x_deg",
                                            "ref_y_deg", "temp_c")})
