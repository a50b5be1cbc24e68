"""What every instrument driver offers the daemon, whatever its byte protocol.

The one reading model (`Reading`), the device's identity and health as `/devices` reports
them, and the driver protocols per role: each driver class names the protocol it implements
as a base class, so mypy holds it to every member, and the bench reaches its drivers through
these protocols. Drivers convert units at their edge: angles
leave a driver in degrees, whatever the wire carried (BCD degrees, milliradians, pulses).
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from typing import Literal, Protocol, runtime_checkable

DeviceState = Literal["connected", "reconnecting", "failed"]
AxisState = Literal["ready", "moving", "homing", "hard_limit", "error"]


@dataclass(frozen=True)
class Reading:
    """One reading of one instrument, stamped when its last byte arrived.

    `bench_s` is bench time (service.clock), `time_utc` real time. Only the fields the
    instrument measures are set: a biaxial inclinometer x_deg/y_deg (and temp_c where the
    protocol carries it in the same answer), the triaxial module sx/sy/sz (sines, in g),
    the ADC counts.
    """

    role: str
    bench_s: float
    time_utc: dt.datetime
    x_deg: float | None = None
    y_deg: float | None = None
    sx: float | None = None
    sy: float | None = None
    sz: float | None = None
    counts: float | None = None
    temp_c: float | None = None
    # Family (B) status: 0 valid, 1 out of range, 2 not settled.
    status: int | None = None
    # An ambient sensor's relative humidity of the air (its temp_c is the air's temperature).
    humidity_pct: float | None = None


@dataclass(frozen=True)
class DeviceIdentity:
    """What the instrument says it is; recorded on the device record and in certificates.

    Where it is connected is not part of it (a port can change between starts). An instrument that
    reports no serial number (family A answers at its bus address only) has `serial` None and its
    `address`; the lab's database then knows it by bench, role and address (`register_key`).
    """

    model: str
    serial: str | None
    firmware: str | None = None
    # the bus address it answered at, e.g. "0x00", when it reports no serial
    address: str | None = None

    def register_key(self, bench: str, role: str) -> str:
        """The serial the lab's device records know this instrument by."""
        if self.serial is not None:
            return self.serial
        return f"{bench}.{role} (address {self.address})"

    def in_words(self) -> str:
        """As a person reads it: model, serial number (or that it has none), firmware."""
        serial = (
            f"s/n {self.serial}"
            if self.serial is not None
            else f"no serial number (bus address {self.address})"
        )
        return f"{self.model}, {serial}" + (f", firmware {self.firmware}" if self.firmware else "")


@dataclass
class DeviceCounters:
    frames: int = 0
    bad_checksum: int = 0
    resyncs: int = 0
    timeouts: int = 0
    reconnects: int = 0
    # Good frames from an address (or controller axis) that no driver on the port owns.
    wrong_address: int = 0


@dataclass
class DeviceStatus:
    """One device's health as GET /devices reports it."""

    role: str
    port: str
    protocol: str
    state: DeviceState = "reconnecting"
    last_frame_utc: dt.datetime | None = None
    counters: DeviceCounters = field(default_factory=DeviceCounters)
    identity: DeviceIdentity | None = None
    error: str | None = None  # the last failure, in words


@runtime_checkable
class Driver(Protocol):
    """What the daemon asks of every role's driver: its health, its life cycle, its identity."""

    role: str
    protocol: str  # the family's byte protocol: binary, rs485, adc, controller

    @property
    def status(self) -> DeviceStatus: ...

    async def start(self) -> None: ...

    async def close(self) -> None: ...

    async def identify(self) -> DeviceIdentity: ...


@runtime_checkable
class Sensor(Driver, Protocol):
    """A role that measures: readings kept from automatic output or polling, and a mark in their
    stream."""

    def latest(self) -> Reading | None:
        """The newest reading from the instrument's automatic output or polling; no I/O."""
        ...

    def readings_after(self, bench_s: float) -> list[Reading]:
        """The readings kept that are stamped after `bench_s` (bench seconds), oldest first; no
        I/O."""
        ...

    async def sync(self) -> float:
        """A mark (bench seconds) after which every reading was made after the call."""
        ...

    async def stop_polling(self) -> None:
        """No more reads of its own: the line is the caller's."""
        ...


@runtime_checkable
class TiltSensor(Sensor, Protocol):
    """reference_sensor, measurement_sensor (family A) and turntable_sensor (family B)."""

    resolution_deg: float  # the last digit the protocol carries: an uncertainty budget's resolution

    async def read_tilt(self) -> Reading: ...

    async def read_temperature(self) -> float: ...

    async def set_relative_zero(self) -> None: ...

    async def set_absolute_zero(self) -> None: ...


@runtime_checkable
class TriaxialSensor(Sensor, Protocol):
    """triaxial_sensor: family (A) with command 0x07 (sines of the three axes)."""

    async def read_sines(self) -> Reading: ...

    async def read_temperature(self) -> float: ...


@runtime_checkable
class TemperatureOnRequest(Sensor, Protocol):
    """A sensor whose angle frames carry no temperature (family A): it is asked for one (0x06)."""

    answers_temperature: bool  # False once the instrument is found to lack the command

    async def read_temperature(self) -> float: ...


@runtime_checkable
class AmbientSensor(Sensor, Protocol):
    """A thermo-hygrometer reading the laboratory's air; its standard uncertainties as the lab
    states them."""

    standard_uncertainty_c: float
    standard_uncertainty_pct: float

    async def read_ambient(self) -> Reading: ...


@runtime_checkable
class AnalogSensor(Sensor, Protocol):
    """adc_sensor: family (C)."""

    async def read_counts(self, conversions: int = 1) -> Reading: ...


@runtime_checkable
class MotionAxis(Driver, Protocol):
    """One axis of a family (D) controller: a swing stage (1 upper x, 2 lower y) or the rotary table
    (3)."""

    axis: int
    pulse_deg: float

    async def move_to_pulses(self, pulses: int) -> None: ...

    async def move_to_deg(self, angle_deg: float) -> int:
        """Start a move to the nearest whole pulse; returns the pulses commanded."""
        ...

    async def position_pulses(self) -> int: ...

    async def position_deg(self) -> float: ...

    async def state(self) -> AxisState: ...

    async def wait_until_idle(self, timeout_s: float) -> float:
        """Return once the axis is ready; raise on a hard limit, an error, or the timeout (bench
        seconds). Returns the bench time it stopped: between the last state query that found it
        moving and the first that found it ready (their midpoint), however late the answers were
        read."""
        ...

    async def stop(self) -> None: ...

    async def home(self) -> None: ...


@runtime_checkable
class TwoAxisStage(Driver, Protocol):
    """The `stage` role: the upper (x) and lower (y) swing stages of one controller, moved
    together."""

    @property
    def x(self) -> MotionAxis: ...

    @property
    def y(self) -> MotionAxis: ...

    async def move_to_deg(self, x_deg: float, y_deg: float) -> tuple[int, int]:
        """Start both axes; returns the pulses commanded."""
        ...

    async def position_deg(self) -> tuple[float, float]: ...

    async def wait_until_idle(self, timeout_s: float) -> float:
        """Both axes ready; the later of their ready queries' bench times."""
        ...

    async def stop(self) -> None: ...

    async def home(self) -> None: ...
