"""The instrument tests' bench speed, and a simulated bench's drivers run as the daemon does."""

from __future__ import annotations

import asyncio

from service.instruments.wiring import open_bench

# bench seconds per real second: moves and output intervals are short, the rules the same
SPEED = 20.0


def run_with_devices(sim, body, config=None):
    """Open the bench's drivers (as the daemon would), run `await body(devices)`, close them."""

    async def main():
        devices = open_bench(config or sim.config, sim.clock)
        await devices.start()
        try:
            return await body(devices)
        finally:
            await devices.close()

    return asyncio.run(main())


async def at_rest(sim) -> None:
    """Wait, on the bench clock, until the last move's settling transient has died out: the table
    rings and each sensor lags it after every move (the preset's settling), and a reading made at
    rest is what these tests compare with the world's truth."""
    await sim.clock.sleep(sim.world.settling.lasts_s())


async def eventually_async(check, what: str, attempts: int = 200, pause_s: float = 0.02):
    """Poll an async or plain condition until it holds (no wall-clock assertion: a bounded number of
    tries)."""
    for _ in range(attempts):
        got = check()
        if asyncio.iscoroutine(got):
            got = await got
        if got:
            return got
        await asyncio.sleep(pause_s)
    raise AssertionError(f"never happened: {what}")
