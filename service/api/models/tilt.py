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
    """The table tilt in the reference sensor's frame with its uncertainties (GUM): per axis the
    standard uncertainty u, the expanded uncertainty U = k·u for a coverage probability of 95 %, the
    coverage factor k and the effective degrees of freedom it is Student's t at."""

    x_deg: float
    y_deg: float
    standard_uncertainty_x_deg: float | None = Field(
        None, description="standard uncertainty u of x_deg"
    )
    standard_uncertainty_y_deg: float | None = Field(
        None, description="standard uncertainty u of y_deg"
    )
    expanded_uncertainty_x_deg: float | None = Field(
        None, description="expanded uncertainty U = k·u of x_deg (coverage_probability)"
    )
    expanded_uncertainty_y_deg: float | None = Field(
        None, description="expanded uncertainty U = k·u of y_deg (coverage_probability)"
    )
    coverage_factor_x: float | None = Field(None, description="k of expanded_uncertainty_x_deg")
    coverage_factor_y: float | None = Field(None, description="k of expanded_uncertainty_y_deg")
    coverage_probability: float | None = None
    degrees_of_freedom_x: float | None = Field(
        None,
        description="effective degrees of freedom of x (Welch-Satterthwaite); null when infinite",
    )
    degrees_of_freedom_y: float | None = Field(
        None, description="effective degrees of freedom of y; null when infinite"
    )
    n_readings: int | None = Field(
        None, description="with average_s: how many readings the mean is of"
    )
    window_s: float | None = Field(
        None,
        description="with average_s: the bench seconds the mean's readings span "
        "(shorter than average_s where the stage moved since, or fewer are kept)",
    )
    u_x_deg: float | None = Field(
        None,
        deprecated=True,
        description="deprecated: the EXPANDED uncertainty of x_deg"
        " (expanded_uncertainty_x_deg); kept for this release",
    )
    u_y_deg: float | None = Field(
        None,
        deprecated=True,
        description="deprecated: the EXPANDED uncertainty of y_deg"
        " (expanded_uncertainty_y_deg); kept for this release",
    )
    k: float | None = Field(
        None, deprecated=True, description="deprecated: coverage_factor_x; kept for this release"
    )
    k_y: float | None = Field(
        None, deprecated=True, description="deprecated: coverage_factor_y; kept for this release"
    )


class RawReadings(Answer):
    measurement_sensor: AxisPair | None
    reference_sensor: AxisPair | None


class ReferenceTilt(Answer):
    """The reference sensor's reading through the active record's model of its own errors."""

    x_deg: float | None
    y_deg: float | None
    record_id: int = Field(description="the record whose model of the reference it went through")
    note: str | None = Field(
        None,
        description="why the angles are null (the model needs what the reading lacks), "
        "or that the record's drift is extrapolated far beyond the time it was fitted over",
    )


class CalibrationInUse(Answer):
    record_id: int
    version: int
    method: str
    status: str | None = Field(None, description="the record's status: draft or approved")
    reading_noise: str | None = Field(
        None, description="which estimate of one reading's noise the served uncertainty uses"
    )


class Tilt(Answer):
    bench: str
    time_utc: dt.datetime = Field(
        description="time of the reading (of the answer when there is none)"
    )
    age_s: float | None
    stale: bool | None
    table_tilt: TableTilt | None = Field(
        description="null when no record is active or the sensor is silent; see note"
    )
    raw: RawReadings
    reference_tilt: ReferenceTilt | None = Field(
        None,
        description="the reference sensor's latest reading through the active record's model of "
        "the reference's own errors (a non-linearity, a temperature effect, a drift it "
        "adopted): the table tilt it stands for; null when the record models none (the raw "
        "reading is then the table tilt)",
    )
    temp_c: float | None
    stage: StagePose | None = Field(description="null on a bench without a tilt stage")
    calibration: CalibrationInUse | None
    in_calibrated_range: bool | None = Field(
        None,
        description="whether the corrected tilt lies within the table"
        " tilts the active record was fitted on; null without one",
    )
    note: str
