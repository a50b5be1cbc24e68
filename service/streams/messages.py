"""The JSON messages of the streams, as typed dictionaries: what `/ws/readings` and `/ws/jobs/{id}`
send (each with its `seq` put in front when sent) and what a fleet node publishes of its readings.

They are the very dictionaries the code builds and serialises: the types name their keys, nothing
is added or reordered at run time.
"""

from __future__ import annotations

from typing import Literal, NotRequired, TypedDict

# The corrected table tilt, the tilt through the reference sensor and the active record's status:
# built by service.bench.corrected, whose types name their keys.
from service.bench.corrected import CalibrationInUse, CorrectedTilt, ReferenceTableTilt, TableTilt

# The tilt through the reference sensor: a live message's carries its record (and a note); a
# history row keeps only its angles.
ReferenceTilt = ReferenceTableTilt | TableTilt


class SensorTilt(TypedDict):
    """One sensor's raw reading as a message shows it (degrees; None: the sensor gave none)."""

    x_deg: float | None
    y_deg: float | None


class RawReadings(TypedDict):
    """The raw readings of the bench's two sensors (None: no fresh reading)."""

    measurement_sensor: SensorTilt | None
    reference_sensor: SensorTilt | None


class StageTilt(TypedDict):
    """The stage's pose (degrees) and whether it moves."""

    x_deg: float | None
    y_deg: float | None
    moving: bool


class HistoryReading(TypedDict):
    """A reading as a snapshot's history shows it (the snapshot's head names the calibration)."""

    time_utc: str
    type: Literal["reading"]
    raw: RawReadings
    table_tilt: CorrectedTilt | None
    reference_tilt: ReferenceTilt | None
    in_calibrated_range: bool | None
    stage: StageTilt | None
    temp_c: float | None


class ReadingMessage(HistoryReading):
    """A reading message of the stream without its seq: what clients get and the fleet
    publishes."""

    calibration: CalibrationInUse | None


class PublishedReading(ReadingMessage):
    """A reading message as a fleet node publishes it for another node's clients."""

    bench: str
    node: str
    fleet_seq: int


class SnapshotHead(TypedDict):
    """A snapshot's newest reading and calibration: a local bench's, or (with `node`, without the
    reference tilt and the calibrated range) the newest reading another node published."""

    type: Literal["snapshot"]
    seq: int
    time_utc: str | None
    bench: str
    node: NotRequired[str]
    rate_hz: float
    raw: RawReadings | None
    table_tilt: CorrectedTilt | None
    reference_tilt: NotRequired[ReferenceTilt | None]
    stage: StageTilt | None
    temp_c: float | None
    calibration: CalibrationInUse | None
    in_calibrated_range: NotRequired[bool | None]


class SnapshotMessage(SnapshotHead):
    """The first message of a reading stream (seq 0): its head and the history asked for."""

    history: list[HistoryReading]


class DroppedMessage(TypedDict):
    """Told to a slow client once its queue has room again: how many messages it missed."""

    seq: int
    type: Literal["dropped"]
    count: int
