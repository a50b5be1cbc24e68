"""The reading producer against a bench in memory: a late wake loses no reading.

The producer wakes every half output interval; on a busy event loop a wake can come late, after
several readings arrived. Each of them must still get its message, in order, as a full-rate
client would see it from a bench that was never late.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import time
from typing import Any

from service.clock import Clock
from service.instruments.base import Reading
from service.streams.readings import ReadingProducer

INTERVAL_S = 0.02  # a 50 Hz sensor


class Pose:
    x_deg = 0.0
    y_deg = 0.0
    moving = False


class MemoryBench:
    """What the producer reads of a bench: a clock, readings kept in order, a pose."""

    name = "memory"
    kind = "stage"

    def __init__(self) -> None:
        self.clock = Clock(1.0)
        self.devices = {"measurement_sensor": None, "reference_sensor": None}
        self.kept: dict[str, list[Reading]] = {"measurement_sensor": [], "reference_sensor": []}
        self.pose = Pose()

    def add(self, x_deg: float) -> None:
        now = self.clock.monotonic()
        for role in self.kept:
            self.kept[role].append(
                Reading(
                    role=role,
                    bench_s=now,
                    time_utc=dt.datetime.now(dt.UTC),
                    x_deg=x_deg,
                    y_deg=-x_deg,
                )
            )

    def latest(self, role: str) -> Reading | None:
        return self.kept[role][-1] if self.kept.get(role) else None

    def readings_after(self, role: str, bench_s: float) -> list[Reading]:
        return [r for r in self.kept[role] if r.bench_s > bench_s]

    def output_interval_s(self, role: str) -> float:
        return INTERVAL_S


async def _run_stalled_producer() -> list[dict[str, Any]]:
    bench = MemoryBench()
    producer = ReadingProducer(bench, lambda: None, queue_size=1000, slow_close_s=60.0)  # type: ignore[arg-type]
    bench.add(0.0)
    producer.start()
    await asyncio.sleep(0.1)
    client = producer.connect(producer.sensor_rate_hz, 0.0)
    await asyncio.sleep(0.05)
    for i in range(1, 4):  # readings the producer wakes for
        bench.add(float(i))
        await asyncio.sleep(INTERVAL_S)
    # the event loop is held: eight readings arrive (a burst) before the next wake
    for i in range(4, 12):
        bench.add(float(i))
        time.sleep(0.005)
    for i in range(12, 15):
        bench.add(float(i))
        await asyncio.sleep(INTERVAL_S)
    await asyncio.sleep(0.1)
    await producer.stop()
    messages = []
    while not client.queue.empty():
        messages.append(json.loads(client.queue.get_nowait()))
    return messages


def test_readings_that_arrive_while_the_loop_is_held_each_get_their_message() -> None:
    got = asyncio.run(_run_stalled_producer())
    readings = [m for m in got if m.get("type") == "reading"]
    # no gap, no dropped notice
    assert [m["seq"] for m in readings] == list(range(1, len(readings) + 1))
    # (a message of a sensor silent past the stale limit carries no reading: a very late wake on a
    # loaded machine)
    values = [
        m["raw"]["measurement_sensor"]["x_deg"] for m in readings if m["raw"]["measurement_sensor"]
    ]
    # every reading after connecting, in order (a sensor silent for an interval has its latest sent
    # again)
    new = [v for i, v in enumerate(values) if i == 0 or v != values[i - 1]]
    assert new[-14:] == [float(i) for i in range(1, 15)], values
