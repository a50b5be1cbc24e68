"""What asking a family (A) sensor its temperature (0x06) does to its automatic output.

A simulated stage bench at 20x (25 Hz output, 500 frames a real second, as the daemon's tests
run it) is read for 5 s while the reference sensor is asked its temperature every N seconds;
prints readings per second and the largest gap between consecutive readings.

    python benchmarks/bench_temperature_asks.py [--seconds 5]
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
from pathlib import Path

from service.clock import Clock
from service.instruments.sim import start_simulated_bench
from service.instruments.wiring import open_bench

SPEED = 20.0


async def measure(ask_every_s: float | None, seconds: float) -> str:
    clock = Clock(SPEED)
    with tempfile.TemporaryDirectory() as d:
        sim = start_simulated_bench(
            "seed000", "stage", clock, directory=Path(d) / "ports", output_rate_hz=25
        )
        devices = open_bench(sim.config, clock)
        await devices.start()
        try:
            sensor = devices.reference_sensor
            await asyncio.sleep(0.5)
            t0, b0, asks = time.monotonic(), clock.monotonic(), 0
            while time.monotonic() - t0 < seconds:
                if ask_every_s is not None:
                    await sensor.read_temperature()
                    asks += 1
                await asyncio.sleep(ask_every_s or 0.05)
            got = sensor.readings_after(b0)
        finally:
            await devices.close()
            sim.close()
    gaps = [clock.real_seconds(b.bench_s - a.bench_s) for a, b in zip(got, got[1:])]
    what = "never asked" if ask_every_s is None else f"asked every {ask_every_s:g} s"
    return (
        f"{what:>20}: {asks:4d} asks, {len(got) / seconds:5.0f} readings/s, "
        f"largest gap {max(gaps) * 1e3:5.1f} ms, mean gap {sum(gaps) / len(gaps) * 1e3:.2f} ms"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    args = ap.parse_args()
    for every in (None, 1.0, 0.25, 0.01):
        print(asyncio.run(measure(every, args.seconds)), flush=True)


if __name__ == "__main__":
    main()
