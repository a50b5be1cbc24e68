"""Bodies of /benches and /devices."""

from __future__ import annotations

import datetime as dt

from pydantic import Field

from service.api.models.base import Answer


class Simulated(Answer):
    scenario: str | None
    scenarios: list[str]
    speed: float = Field(description="how many times faster than real time the simulation runs")


class BenchInfo(Answer):
    name: str
    kind: str = Field(description="stage or rotary")
    roles: list[str]
    state: str = Field(description="ready, busy, connecting or degraded")
    held_by: str | None = Field(description="the job or action holding the bench")
    description: str | None = None
    simulated: Simulated | None = Field(
        None, description="for a simulated bench: its scenario and speed"
    )
    node: str | None = Field(None, description="the daemon (TILTLAB_NODE) that runs the bench")
    online: bool = Field(
        True, description="whether that daemon is heard from (always true for its own benches)"
    )


class Benches(Answer):
    benches: list[BenchInfo]


class Counters(Answer):
    frames: int
    bad_checksum: int
    resyncs: int
    timeouts: int
    reconnects: int


class Identity(Answer):
    """What the instrument reported itself to be; where it is connected is the device's `port`."""

    model: str | None
    serial: str | None = Field(
        description="the serial number the instrument reported; null when it reports none"
    )
    firmware: str | None
    address: str | None = Field(
        None,
        description="the bus address it answered at, for an instrument without a"
        " serial number (e.g. 0x00)",
    )


class DeviceStatus(Answer):
    role: str
    port: str | None
    protocol: str | None
    state: str = Field(description="connected, reconnecting or failed")
    last_frame_utc: dt.datetime | None
    counters: Counters
    identity: Identity | None
    error: str | None


class Devices(Answer):
    bench: str
    devices: list[DeviceStatus]
