"""A bench's ambient sensor: a thermo-hygrometer of family (B) on a pseudo-terminal, read through
its driver as on hardware; its readings follow the simulated air within the instrument's noise and
digits."""

from __future__ import annotations

import asyncio

import pytest

from service.clock import Clock
from service.instruments.sim import start_simulated_bench
from service.instruments.transport import DeviceError
from tests.helpers.instruments import SPEED, run_with_devices


@pytest.mark.pty
def test_the_ambient_sensor_reads_the_air_it_is_in(tmp_path):
    sim = start_simulated_bench(
        "seed000", "stage", Clock(SPEED), directory=tmp_path / "ports", ambient=True
    )
    try:
        assert sim.config.role("ambient_sensor").standard_uncertainty_c == 0.1  # the role's default
        air = sim.ports["ambient_sensor"].firmware

        async def body(dev):
            sensor = dev.ambient_sensor()
            assert sensor is not None and dev.tilt_sensor("ambient_sensor") is None
            ident = await sensor.identify()
            assert (ident.model, ident.serial) == ("TH-200SIM", "SIM-TH01")
            readings = [await sensor.read_ambient() for _ in range(20)]
            for r in readings:
                # the instrument's noise (0.02 °C, 0.3 %) within 5 sigma, and the digits it carries
                assert abs(r.temp_c - air.truth_c(r.bench_s)) < 5 * 0.02 + 0.005
                assert abs(r.humidity_pct - air.truth_pct(r.bench_s)) < 5 * 0.3 + 0.05
                assert round(r.temp_c, 2) == r.temp_c and round(r.humidity_pct, 1) == r.humidity_pct
            # polled readings are kept for a job to summarise
            await asyncio.sleep(0.3)
            assert sensor.readings_after(readings[0].bench_s)

        run_with_devices(sim, body)
    finally:
        sim.close()


def test_an_out_of_range_reading_is_refused_not_kept(tmp_path):
    from service.instruments import rs485

    sim = start_simulated_bench(
        "seed000",
        "stage",
        Clock(SPEED),
        directory=tmp_path / "ports",
        ambient=True,
        transport="loopback",
    )
    try:
        air = sim.ports["ambient_sensor"].firmware
        plain = air.handle

        def out_of_range(data: bytes) -> list[bytes]:
            return [
                rs485.encode(rs485.Rs485Ambient(1, 99.0, 0.0, 1)) if b"TH" in f else f
                for f in plain(data)
            ]

        air.handle = out_of_range

        async def body(dev):
            sensor = dev.ambient_sensor()
            await sensor.stop_polling()
            with pytest.raises(DeviceError, match="out of range"):
                await sensor.read_ambient()
            assert sensor.latest() is None

        run_with_devices(sim, body)
    finally:
        sim.close()
