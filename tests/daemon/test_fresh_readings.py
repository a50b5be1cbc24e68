"""Waiting for a sensor's next readings: a slow sensor that keeps answering is read to the end, a
silent one fails the wait naming the role, its port and how long it was silent."""

from __future__ import annotations

import asyncio
import datetime as dt
from types import SimpleNamespace

import pytest

from service.bench.readings import fresh_readings
from service.bench.runtime import DeviceNotAnswering
from service.clock import Clock
from service.instruments.base import Reading


class _Sensor:
    """A bench of one role whose `count` readings come `every_real_s` real seconds apart."""

    def __init__(self, clock: Clock, every_real_s: float, count: int) -> None:
        self.clock = clock
        self.readings: list[Reading] = []
        self.every_real_s = every_real_s
        self.count = count
        self.devices = {
            "reference_sensor": SimpleNamespace(
                status=SimpleNamespace(port="/dev/ttyUSB3", state="connected", error=None)
            )
        }

    def readings_after(self, role: str, bench_s: float) -> list[Reading]:
        return [reading for reading in self.readings if reading.bench_s > bench_s]

    def output_interval_s(self, role: str) -> float:
        return 0.1

    async def answer(self) -> None:
        for _ in range(self.count):
            await asyncio.sleep(self.every_real_s)
            self.readings.append(
                Reading(
                    "reference_sensor",
                    self.clock.monotonic(),
                    dt.datetime.now(dt.UTC),
                    x_deg=0.0,
                    y_deg=0.0,
                )
            )


async def _wait(sensor: _Sensor, n: int) -> list[Reading]:
    feeder = asyncio.create_task(sensor.answer())
    try:
        return await fresh_readings(
            sensor,  # type: ignore[arg-type]
            "reference_sensor",
            n,
            after_bench_s=-1.0,
            timeout_s=1.0,
        )
    finally:
        feeder.cancel()


def test_a_slow_sensor_that_keeps_answering_is_read_to_the_end():
    """Each reading 1.2 real s after the last: the wait (2 real s at least) is for the next
    reading, not for all four (4.8 s), so the sensor is read, not failed."""
    sensor = _Sensor(Clock(20.0), every_real_s=1.2, count=4)
    got = asyncio.run(_wait(sensor, 4))
    assert len(got) == 4
    assert [reading.bench_s for reading in got] == sorted(reading.bench_s for reading in got)


def test_a_sensor_that_falls_silent_fails_the_wait_naming_it():
    sensor = _Sensor(Clock(20.0), every_real_s=0.3, count=2)
    with pytest.raises(DeviceNotAnswering) as raised:
        asyncio.run(_wait(sensor, 4))
    message = str(raised.value)
    assert "reference_sensor on /dev/ttyUSB3: no reading for 2 s (connected)" == message
