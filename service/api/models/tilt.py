"""Body of GET /tilt, and the angle pairs other answers share."""

from __future__ import annotations

import datetime as dt

from pydantic import Field

from service.api.models.base import Answer


class AxisPair(Answer):
    x_deg: float | None
    y_deg: float | None


class StagePose(Answer):
    x_deg: float | None
    y_deg: float | None
    moving: bool


class TableTilt(Answer):
    """The table tilt in the reference sensor's frame with its expanded uncertainties (95 %)."""

    x_deg: float
    y_deg: float
    u_x_deg: float | None = None
    u_y_deg: float | None = None
    k: float | None = Field(None, description="coverage factor of u_x_deg")
    k_y: float | None = Field(None, description="coverage factor of u_y_deg")
    coverage_probability: float | None = None


class RawReadings(Answer):
    measurement_sensor: AxisPair | None
    reference_sensor: AxisPair | None


class CalibrationInUse(Answer):
    record_id: int
    version: int
    method: str
    status: str | None = Field(None, description="the record's status: draft or approved")


class Tilt(Answer):
    bench: str
    time_utc: dt.datetime = Field(description="time of the reading (of the answer when there is none)")
    age_s: float | None
    stale: bool | None
    table_tilt: TableTilt | None = Field(description="null when no record is active or the sensor is silent; see note")
    raw: RawReadings
    temp_c: float | None
    stage: StagePose | None = Field(description="null on a bench without a tilt stage")
    calibration: CalibrationInUse | None
    in_calibrated_range: bool | None = Field(None, description="whether the corrected tilt lies within the table"
                                             " tilts the active record was fitted on; null without one")
    note: str
