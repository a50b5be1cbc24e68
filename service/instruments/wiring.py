"""A bench's instruments, opened from its configuration: one driver per role, ports shared only on a bus."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterator
from typing import Any

from service.clock import Clock
from service.instruments import adc, binary, controller, rs485
from service.instruments.base import DeviceStatus
from service.instruments.bench_config import (
    DEFAULT_BAUD,
    PROTOCOL_OF_ROLE,
    AdcRole,
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
    StageController,
    TriaxialModule,
)
from service.instruments.transport import PortRegistry, SerialPort

PARSERS: dict[str, Callable[[bytes], Any]] = {"binary": binary.parse_answers, "rs485": rs485.parse_answers, "adc": adc.parse_answers,
           "controller": controller.parse_answers}


class BenchDevices:
    """The drivers of one bench by role (`devices.stage`, `devices["reference_sensor"]`)."""

    def __init__(self, config: BenchConfig, clock: Clock, drivers: dict) -> None:
        self.config = config
        self.clock = clock
        self.drivers = drivers

    def __getitem__(self, role: str):
        return self.drivers[role]

    def __getattr__(self, role: str):
        drivers = self.__dict__.get("drivers", {})
        if role in drivers:
            return drivers[role]
        raise AttributeError(role)

    def __contains__(self, role: str) -> bool:
        return role in self.drivers

    def __iter__(self) -> Iterator[str]:
        return iter(self.drivers)

    async def start(self) -> None:
        await asyncio.gather(*(d.start() for d in self.drivers.values()))

    async def close(self) -> None:
        for d in self.drivers.values():
            await d.close()

    def status(self) -> list[DeviceStatus]:
        return [d.status for d in self.drivers.values()]

    async def __aenter__(self) -> BenchDevices:
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()


def _port(registry: PortRegistry, role: str, spec: PortRole) -> SerialPort:
    family = PROTOCOL_OF_ROLE[role]
    return registry.get(spec.where, PARSERS[family], family=family, baud=spec.baud or DEFAULT_BAUD[family],
                        usb_serial=spec.usb_serial)


def _limits(pair: list[float] | None) -> tuple[float, float] | None:
    return (float(pair[0]), float(pair[1])) if pair else None


def make_driver(role: str, spec: PortRole, config: BenchConfig, clock: Clock, registry: PortRegistry):
    port = _port(registry, role, spec)
    t = spec.timeout_s
    if isinstance(spec, BinaryInclinometerRole):
        cls = TriaxialModule if role == "triaxial_sensor" else BinaryInclinometer
        return cls(role, port, clock, t, spec.address, spec.output_rate_hz)
    if isinstance(spec, Rs485InclinometerRole):
        return Rs485Inclinometer(role, port, clock, t, int(spec.address, 16), spec.poll_rate_hz)
    if isinstance(spec, AdcRole):
        return AdcSensor(role, port, clock, t, spec.conversions_per_reading, spec.poll_rate_hz)
    if isinstance(spec, StageControllerRole):
        hw = config.stage_bench()
        x = ControllerAxis(role, port, clock, t, 1, hw.pulse_x_deg, spec.velocity_pulses_per_s,
                           _limits(spec.soft_limits_x_deg))
        y = ControllerAxis(role, port, clock, t, 2, hw.pulse_y_deg, spec.velocity_pulses_per_s,
                           _limits(spec.soft_limits_y_deg))
        return StageController(role, x, y)
    assert isinstance(spec, RotaryTableRole)
    return ControllerAxis(role, port, clock, t, spec.axis, spec.pulse_deg, spec.velocity_pulses_per_s)


def open_bench(bench_config: BenchConfig, clock: Clock) -> BenchDevices:
    """Drivers for every role of the bench; nothing is opened before `await devices.start()`."""
    registry = PortRegistry()
    drivers = {role: make_driver(role, spec, bench_config, clock, registry)
               for role, spec in bench_config.role_specs.items()}
    return BenchDevices(bench_config, clock, drivers)
