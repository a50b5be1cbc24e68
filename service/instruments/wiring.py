"""A bench's instruments, opened from its configuration: one driver per role, ports shared only on a
bus."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterator, Mapping
from typing import Any

from service.clock import Clock
from service.instruments import adc, binary, controller, rs485
from service.instruments.base import (
    AmbientSensor,
    DeviceStatus,
    Driver,
    MotionAxis,
    Sensor,
    TemperatureOnRequest,
    TiltSensor,
    TwoAxisStage,
)
from service.instruments.bench_config import (
    DEFAULT_BAUD,
    PROTOCOL_OF_ROLE,
    AdcRole,
    AmbientSensorRole,
    BenchConfig,
    BinaryInclinometerRole,
    PortRole,
    RotaryTableRole,
    Rs485InclinometerRole,
    StageControllerRole,
)
from service.instruments.drivers import (
    AdcSensor,
    BinaryInclinometer,
    ControllerAxis,
    Rs485Inclinometer,
    Rs485Thermohygrometer,
    StageController,
    TriaxialModule,
)
from service.instruments.transport import PortRegistry, SerialPort

PARSERS: dict[str, Callable[[bytes], Any]] = {
    "binary": binary.parse_answers,
    "rs485": rs485.parse_answers,
    "adc": adc.parse_answers,
    "controller": controller.parse_answers,
}

# Every family's driver class, as `make_driver` hands them out (TriaxialModule is a
# BinaryInclinometer).
RoleDriver = (
    BinaryInclinometer
    | Rs485Inclinometer
    | Rs485Thermohygrometer
    | AdcSensor
    | ControllerAxis
    | StageController
)


class BenchDevices:
    """The drivers of one bench by role (`devices.stage`, `devices["reference_sensor"]`), and each
    role as the protocol it plays (`devices.sensor(role)`, `devices.stage_axes()`,
    `devices.axis(role)`)."""

    def __init__(self, config: BenchConfig, clock: Clock, drivers: Mapping[str, Driver]) -> None:
        self.config = config
        self.clock = clock
        self.drivers: dict[str, Driver] = dict(drivers)
        # Sorted by protocol once: the bench asks for a role as what it plays, many times a second.
        self._sensors = {
            role: driver for role, driver in self.drivers.items() if isinstance(driver, Sensor)
        }
        self._axes = {
            role: driver for role, driver in self.drivers.items() if isinstance(driver, MotionAxis)
        }
        self._stages = {
            role: driver
            for role, driver in self.drivers.items()
            if isinstance(driver, TwoAxisStage)
        }

    def __getitem__(self, role: str) -> Driver:
        return self.drivers[role]

    def __getattr__(self, role: str) -> Any:
        drivers = self.__dict__.get("drivers", {})
        if role in drivers:
            return drivers[role]
        raise AttributeError(role)

    def __contains__(self, role: str) -> bool:
        return role in self.drivers

    def __iter__(self) -> Iterator[str]:
        return iter(self.drivers)

    def sensor(self, role: str) -> Sensor:
        """The role's driver as a source of readings (KeyError if the bench has none that
        measures)."""
        return self._sensors[role]

    def tilt_sensor(self, role: str) -> TiltSensor | None:
        """The role's driver if it reads tilt and temperature (a biaxial inclinometer), else
        None."""
        driver = self._sensors.get(role)
        return driver if isinstance(driver, TiltSensor) else None

    def temperature_on_request(self, role: str) -> TemperatureOnRequest | None:
        """The role's driver if its temperature must be asked for (family A), else None."""
        driver = self._sensors.get(role)
        return driver if isinstance(driver, TemperatureOnRequest) else None

    def ambient_sensor(self) -> AmbientSensor | None:
        """The bench's thermo-hygrometer (role ambient_sensor), None where it has none."""
        driver = self._sensors.get("ambient_sensor")
        return driver if isinstance(driver, AmbientSensor) else None

    def axis(self, role: str) -> MotionAxis:
        """A role of one controller axis (the rotary table)."""
        return self._axes[role]

    def stage_axes(self, role: str = "stage") -> TwoAxisStage:
        """The two swing stages moved together."""
        return self._stages[role]

    async def start(self) -> None:
        await asyncio.gather(*(driver.start() for driver in self.drivers.values()))

    async def close(self) -> None:
        for driver in self.drivers.values():
            await driver.close()

    def status(self) -> list[DeviceStatus]:
        return [driver.status for driver in self.drivers.values()]

    async def __aenter__(self) -> BenchDevices:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


def _port(registry: PortRegistry, role: str, spec: PortRole) -> SerialPort:
    family = PROTOCOL_OF_ROLE[role]
    return registry.get(
        spec.where,
        PARSERS[family],
        family=family,
        baud=spec.baud or DEFAULT_BAUD[family],
        usb_serial=spec.usb_serial,
    )


def _limits(pair: list[float] | None) -> tuple[float, float] | None:
    return (float(pair[0]), float(pair[1])) if pair else None


def make_driver(
    role: str, spec: PortRole, config: BenchConfig, clock: Clock, registry: PortRegistry
) -> RoleDriver:
    """The driver of one role, as its family's class (a probe reaches its port too)."""
    port = _port(registry, role, spec)
    t = spec.timeout_s
    if isinstance(spec, BinaryInclinometerRole):
        if role == "triaxial_sensor":
            return TriaxialModule(role, port, clock, t, spec.address, spec.output_rate_hz)
        return BinaryInclinometer(role, port, clock, t, spec.address, spec.output_rate_hz)
    if isinstance(spec, Rs485InclinometerRole):
        return Rs485Inclinometer(role, port, clock, t, int(spec.address, 16), spec.poll_rate_hz)
    if isinstance(spec, AmbientSensorRole):
        return Rs485Thermohygrometer(
            role,
            port,
            clock,
            t,
            int(spec.address, 16),
            spec.poll_rate_hz,
            spec.standard_uncertainty_c,
            spec.standard_uncertainty_pct,
        )
    if isinstance(spec, AdcRole):
        return AdcSensor(role, port, clock, t, spec.conversions_per_reading, spec.poll_rate_hz)
    if isinstance(spec, StageControllerRole):
        hw = config.stage_bench()
        x = ControllerAxis(
            role,
            port,
            clock,
            t,
            1,
            hw.pulse_x_deg,
            spec.velocity_pulses_per_s,
            _limits(spec.soft_limits_x_deg),
        )
        y = ControllerAxis(
            role,
            port,
            clock,
            t,
            2,
            hw.pulse_y_deg,
            spec.velocity_pulses_per_s,
            _limits(spec.soft_limits_y_deg),
        )
        return StageController(role, x, y)
    assert isinstance(spec, RotaryTableRole)
    return ControllerAxis(
        role, port, clock, t, spec.axis, spec.pulse_deg, spec.velocity_pulses_per_s
    )


def open_bench(bench_config: BenchConfig, clock: Clock) -> BenchDevices:
    """Drivers for every role of the bench; nothing is opened before `await devices.start()`."""
    registry = PortRegistry()
    drivers: dict[str, Driver] = {
        role: make_driver(role, spec, bench_config, clock, registry)
        for role, spec in bench_config.role_specs.items()
    }
    return BenchDevices(bench_config, clock, drivers)
