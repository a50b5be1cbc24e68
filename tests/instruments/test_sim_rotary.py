"""The rotary bench through pseudo-terminals: axis 3 without limits, the triaxial module's sines,
and three addressed RS-485 inclinometers on one bus."""

from __future__ import annotations

import asyncio

import pytest

from service.instruments import rs485
from service.instruments.bench_config import parse_bench_config
from tests.helpers.instruments import run_with_devices


def test_rotary_table_turns_without_limit_and_the_sines_follow(rotary_sim):
    async def body(dev):
        table = dev.rotary_table
        assert (await table.identify()).model == "RT-360SIM"
        lo, hi = await table.soft_limits_pulses()
        assert lo < -(10**9) and hi > 10**9
        before = await dev.triaxial_sensor.read_sines()
        await table.move_to_deg(400.0)  # past a full turn
        await table.wait_until_idle(120)
        assert await table.position_deg() == pytest.approx(400.0)
        assert rotary_sim.world.table_deg == pytest.approx(400.0)
        after = await dev.triaxial_sensor.read_sines()
        truth = rotary_sim.world.sines(noisy=False)
        assert (after.sx, after.sy, after.sz) == pytest.approx(truth, abs=0.002)
        assert abs(after.sx - before.sx) > 0.01  # the module turned with the table
        assert after.sx**2 + after.sy**2 + after.sz**2 == pytest.approx(1.0, abs=0.01)

    run_with_devices(rotary_sim, body)


def _bus_config(sim, addresses):
    bus = sim.port_path("turntable_sensor")
    lines = [
        "[benches.bus]",
        'kind = "rotary"',
        f'[benches.bus.roles.rotary_table]\nport = "{sim.port_path("rotary_table")}"\naxis = 3',
        f'[benches.bus.roles.turntable_sensor]\nport = "{bus}"\naddress = "{addresses[0]:02X}"',
    ]
    cfg = parse_bench_config(__import__("tomllib").loads("\n".join(lines))).bench("bus")
    return cfg, bus


def test_three_addressed_inclinometers_share_one_bus(rotary_sim):
    """One port, one request in flight: each instrument answers only to its address."""
    from service.instruments.transport import PortRegistry
    from service.instruments.wiring import make_driver

    async def main():
        cfg, bus = _bus_config(rotary_sim, (1, 2, 3))
        registry = PortRegistry()
        spec = cfg.role("turntable_sensor")
        sensors = [
            make_driver(
                "turntable_sensor",
                spec.model_copy(update={"address": f"{a:02X}", "poll_rate_hz": 50.0}),
                cfg,
                rotary_sim.clock,
                registry,
            )
            for a in (1, 2, 3)
        ]
        assert len({id(s.port) for s in sensors}) == 1  # one owner of the bus
        for s in sensors:
            await s.start()
        try:
            idents = await asyncio.gather(*(s.identify() for s in sensors))
            assert [i.serial for i in idents] == ["SIM-B01", "SIM-B02", "SIM-B03"]
            readings = await asyncio.gather(*(s.read_tilt() for s in sensors for _ in range(5)))
            for k in range(len(sensors)):
                mine = readings[5 * k : 5 * k + 5]
                x_mrad, y_mrad = rotary_sim.world.turntable_mrad(k + 1, noisy=False)
                for r in mine:
                    assert rs485.deg_to_mrad(r.x_deg) == pytest.approx(x_mrad, abs=0.005)
                    assert rs485.deg_to_mrad(r.y_deg) == pytest.approx(y_mrad, abs=0.005)
            # The three sit at different azimuths, so they read differently: no answer went to the
            # wrong one.
            firsts = [round(rs485.deg_to_mrad(readings[5 * k].x_deg), 2) for k in range(3)]
            assert len(set(firsts)) == 3
            await sensors[1].set_relative_zero()
            z = await sensors[1].read_tilt()
            assert abs(rs485.deg_to_mrad(z.x_deg)) < 0.005
            other = await sensors[0].read_tilt()
            assert (
                abs(
                    rs485.deg_to_mrad(other.x_deg)
                    - rotary_sim.world.turntable_mrad(1, noisy=False)[0]
                )
                < 0.005
            )
            assert sensors[0].status.counters.timeouts == 0
        finally:
            for s in sensors:
                await s.close()

    asyncio.run(main())


def test_a_bench_with_both_rotary_sensors_opens_from_the_printed_configuration(rotary_sim):
    assert set(rotary_sim.config.role_specs) == {
        "rotary_table",
        "triaxial_sensor",
        "turntable_sensor",
    }

    async def body(dev):
        assert set(dev) == {"rotary_table", "triaxial_sensor", "turntable_sensor"}
        await dev.turntable_sensor.identify()
        s = {x.role: x.state for x in dev.status()}
        assert s == dict.fromkeys(s, "connected")

    run_with_devices(rotary_sim, body)
