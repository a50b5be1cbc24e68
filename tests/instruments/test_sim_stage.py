"""The stage bench end to end through real pseudo-terminals: drivers against simulated firmware."""

from __future__ import annotations

import asyncio

import pytest

from service.instruments import controller
from service.instruments.transport import DeviceError, DeviceRefused
from tests.helpers.instruments import at_rest, eventually_async, run_with_devices

NOISE_TOL_DEG = 0.02  # several sigma of the seed000 sensor and stage noise


def test_readings_follow_the_stage_and_the_physics(stage_sim):
    async def body(dev):
        ident = await dev.stage.identify()
        assert ident.model and ident.serial
        pulses = await dev.stage.move_to_deg(3.0, -2.0)
        assert pulses == (round(3.0 / stage_sim.config.stage_bench().pulse_x_deg), -4000)
        await dev.stage.wait_until_idle(60)
        await at_rest(stage_sim)
        x_deg, y_deg = await dev.stage.position_deg()
        assert (x_deg, y_deg) == pytest.approx(stage_sim.world.pose_deg)
        assert x_deg == pytest.approx(3.0, abs=0.001) and y_deg == pytest.approx(-2.0, abs=0.001)
        truth = stage_sim.world.sample(noisy=False)
        ref = await dev.reference_sensor.read_tilt()
        meas = await dev.measurement_sensor.read_tilt()
        assert ref.x_deg == pytest.approx(truth["ref_x_deg"], abs=NOISE_TOL_DEG)
        assert ref.y_deg == pytest.approx(truth["ref_y_deg"], abs=NOISE_TOL_DEG)
        assert meas.x_deg == pytest.approx(truth["meas_x_deg"], abs=NOISE_TOL_DEG)
        assert meas.y_deg == pytest.approx(truth["meas_y_deg"], abs=NOISE_TOL_DEG)
        temp = await dev.reference_sensor.read_temperature()
        assert temp == pytest.approx(stage_sim.world.temp_c(), abs=0.01)
        return ref

    run_with_devices(stage_sim, body)


def test_automatic_output_keeps_the_latest_reading_fresh(stage_sim):
    async def body(dev):
        sensor = dev.reference_sensor
        first = await eventually_async(sensor.latest, "a first automatic-output frame")
        await eventually_async(lambda: sensor.latest().bench_s > first.bench_s, "a newer frame")
        assert sensor.latest().x_deg is not None and sensor.status.counters.frames >= 2

    run_with_devices(stage_sim, body)


def test_relative_zero_makes_the_present_angle_zero(stage_sim):
    async def body(dev):
        await dev.stage.move_to_deg(2.0, 1.0)
        await dev.stage.wait_until_idle(60)
        await at_rest(stage_sim)
        await dev.reference_sensor.set_relative_zero()
        r = await dev.reference_sensor.read_tilt()
        assert abs(r.x_deg) < NOISE_TOL_DEG and abs(r.y_deg) < NOISE_TOL_DEG
        await dev.reference_sensor.set_absolute_zero()
        r = await dev.reference_sensor.read_tilt()
        assert r.x_deg == pytest.approx(
            stage_sim.world.sample(noisy=False)["ref_x_deg"], abs=NOISE_TOL_DEG
        )

    run_with_devices(stage_sim, body)


def test_moves_take_time_and_report_the_moving_position(stage_sim):
    async def body(dev):
        x = dev.stage.x
        await x.move_to_pulses(12000)  # 3 bench seconds at 4000 pulses/s
        assert await x.state() == "moving"
        seen = await x.position_pulses()
        assert 0 <= seen < 12000
        with pytest.raises(DeviceRefused, match="busy"):
            await x.move_to_pulses(0)
        await x.stop()
        await eventually_async(lambda: _ready(x), "the axis stopped")
        stopped = await x.position_pulses()
        assert 0 <= stopped < 12000 and stage_sim.world.axes[1].position_pulses() == stopped
        await x.home()
        await x.wait_until_idle(60)
        assert await x.position_pulses() == 0

    run_with_devices(stage_sim, body)


async def _ready(axis):
    return await axis.state() == "ready"


def test_soft_limits_refuse_and_hard_limits_stop(stage_sim):
    async def body(dev):
        y = dev.stage.y
        lo, hi = await y.soft_limits_pulses()
        assert (lo, hi) == (-30000, 30000)  # ±15 deg at 0.0005 deg per pulse
        with pytest.raises(DeviceRefused, match="soft limit"):
            await y.move_to_deg(16.0)
        # Widen the soft limit beyond the switch: the move runs into the hard limit.
        await y.port.send(controller.encode(controller.ControllerCommand(2, "SR", 40000)))
        y.velocity_pulses_per_s = 200_000
        await y.configure()
        await y.move_to_pulses(40000)
        with pytest.raises(DeviceError, match="hard limit"):
            await y.wait_until_idle(60)
        assert await y.state() == "hard_limit"
        assert await y.position_pulses() == 31000  # the switch, 0.5 deg past the travel
        with pytest.raises(DeviceRefused, match="hard limit"):
            await y.move_to_pulses(35000)
        await y.move_to_pulses(0)  # away from the switch is allowed
        await y.wait_until_idle(60)
        assert await y.position_pulses() == 0

    run_with_devices(stage_sim, body)


def test_unknown_command_sets_error_1(stage_sim):
    async def body(dev):
        await dev.stage.x.port.send(b"1XY5\r\n")
        assert await dev.stage.x.last_error() == controller.ERR_UNKNOWN
        assert await dev.stage.x.last_error() == controller.ERR_NONE  # read once, then cleared

    run_with_devices(stage_sim, body)


def test_adc_counts_follow_the_table_tilt(stage_sim):
    async def body(dev):
        a = dev.adc_sensor
        ident = await a.identify()
        assert ident.model == "ADC12-SIM"
        one = await a.read_counts(1)
        assert one.counts == int(one.counts) and 0 <= one.counts <= 4095
        mean = await a.read_counts(50)
        expected = stage_sim.world.adc_counts(2000)
        # 5 sigma of a mean of 50 at 25 counts
        assert mean.counts == pytest.approx(expected, abs=20)
        await dev.stage.move_to_deg(0.05, 0.0)
        await dev.stage.wait_until_idle(60)
        moved = await a.read_counts(50)
        assert moved.counts > mean.counts  # tilting the table about x raises the sensor's output

    run_with_devices(stage_sim, body)


def test_status_reports_every_role(stage_sim):
    async def body(dev):
        await asyncio.gather(*(dev[r].identify() for r in dev))
        states = {s.role: s for s in dev.status()}
        assert set(states) == {"reference_sensor", "measurement_sensor", "stage", "adc_sensor"}
        for s in states.values():
            assert s.state == "connected" and s.identity is not None and s.counters.frames > 0
            assert s.port == stage_sim.port_path(s.role)

    run_with_devices(stage_sim, body)


def test_binary_settings_commands_as_the_protocol_says(stage_sim):
    """Address change answered from the old address, a baud code out of the table refused, 0x07
    unanswered."""
    from service.instruments import binary
    from service.instruments.transport import DeviceTimeout

    async def body(dev):
        s = dev.measurement_sensor
        port = s.port

        def req(addr, cmd, arg=None):
            return binary.encode(binary.BinaryRequest(addr, cmd, arg))

        def answer(addr, cmd):
            return lambda m: m.address == addr and m.command == cmd

        refused = await port.request(req(0, binary.SET_BAUD, 0x09), answer(0, 0x8B), 1.0, "baud")
        assert refused.status == binary.STATUS_REFUSED
        with pytest.raises(DeviceTimeout):
            await port.request(
                req(0, binary.READ_SINES), answer(0, 0x87), 0.3, "sines of a biaxial sensor"
            )
        port.own(5)
        moved = await port.request(req(0, binary.SET_ADDRESS, 5), answer(0, 0x8F), 1.0, "address")
        assert moved.status == binary.STATUS_DONE
        at5 = await port.request(req(5, binary.READ_XY), answer(5, 0x84), 1.0, "read at 5")
        assert at5.x_deg is not None
        with pytest.raises(DeviceTimeout):
            await s.read_tilt()  # address 0 no longer answers

    run_with_devices(stage_sim, body)


def test_an_axis_that_is_not_homed_refuses_moves_until_homed(stage_sim):
    async def body(dev):
        x = dev.stage.x
        stage_sim.world.axes[1].homed = False
        with pytest.raises(DeviceRefused, match="not homed"):
            await x.move_to_deg(1.0)
        await x.home()
        assert await x.state() in ("homing", "ready")
        await x.wait_until_idle(60)
        await x.move_to_deg(1.0)
        await x.wait_until_idle(60)
        assert await x.position_deg() == pytest.approx(1.0, abs=0.001)

    run_with_devices(stage_sim, body)


def test_a_lost_state_answer_during_a_move_is_polled_again(stage_sim):
    """One state answer lost on the line (sent from a wrong axis, so the driver may not take it)
    costs one more poll, not the move; the loss is counted."""

    async def body(dev):
        axis = dev.stage.x
        await axis.move_to_deg(2.0)
        stage_sim.faults("stage").wrong_address(1)
        await axis.wait_until_idle(60)
        assert axis.timeouts == 1 and axis.status.counters.wrong_address >= 1
        assert await axis.position_deg() == pytest.approx(2.0, abs=axis.pulse_deg)

    run_with_devices(stage_sim, body)
