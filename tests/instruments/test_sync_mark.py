"""A lagging reader hands out, after a move, readings made during it: the sync mark excludes them.

The reader thread of the reference sensor's port is held while the stage moves (as a loaded
machine would hold it), so frames of the old pose and of the motion wait in the pseudo-terminal
and are stamped only when they are parsed, after the move. Readings stamped after the mark of
`sync()` are of the new pose only; readings stamped after the call but before the mark show
the old ones (the lag the mark exists for).
"""

from __future__ import annotations

import re
import threading

import pytest

from service.instruments.drivers import SYNC_ASKS
from service.instruments.transport import DeviceTimeout
from tests.helpers.instruments import at_rest, eventually_async, run_with_devices

NOISE_TOL_DEG = 0.02


def _hold_reader(port) -> threading.Event:
    """Make the port's reader thread wait (after its next batch) until the returned event is set."""
    release = threading.Event()
    deliver = port._deliver

    def held(messages):
        release.wait(10.0)
        deliver(messages)

    port._deliver = held
    return release


@pytest.mark.parametrize("target", [(4.0, -3.0), (-2.5, 2.0)])
def test_readings_after_the_mark_are_of_the_new_pose(stage_sim, target):
    async def body(dev):
        sensor = dev.reference_sensor
        await eventually_async(sensor.latest, "a first automatic-output frame")
        before = sensor.latest()
        release = _hold_reader(sensor.port)
        await dev.stage.move_to_deg(*target)  # the controller has its own port: its reader runs
        await dev.stage.wait_until_idle(60)
        await at_rest(stage_sim)
        truth = stage_sim.world.sample(noisy=False)
        called_s = sensor.clock.monotonic()
        # the request goes out with the reader still held; it is released once it is written
        threading.Timer(0.2, release.set).start()
        mark = await sensor.sync()
        assert mark > called_s
        late = [r for r in sensor.readings_after(called_s) if r.bench_s <= mark]
        assert late and any(abs(r.x_deg - truth["ref_x_deg"]) > 0.5 for r in late), (
            "the held reader delivered no reading of the old pose after the call: nothing was "
            "tested"
        )
        await eventually_async(
            lambda: len(sensor.readings_after(mark)) >= 5, "five readings after the mark"
        )
        fresh = sensor.readings_after(mark)
        assert all(
            abs(r.x_deg - truth["ref_x_deg"]) < NOISE_TOL_DEG
            and abs(r.y_deg - truth["ref_y_deg"]) < NOISE_TOL_DEG
            for r in fresh
        ), (fresh, truth)
        # the answer is a temperature, carried by the readings from then on
        assert fresh[0].temp_c == pytest.approx(stage_sim.world.temp_c(), abs=0.05)
        assert before.bench_s < called_s

    run_with_devices(stage_sim, body)


def test_an_answer_owed_from_before_the_call_does_not_mark_the_stream(stage_sim):
    """A temperature request timed out before the call (the reader held up), and its answer waits in
    the line behind it with frames made during a move. The first answer the mark's request gets is
    that old one; readings counted after the mark are still of the new pose only."""

    async def body(dev):
        sensor = dev.reference_sensor
        await eventually_async(sensor.latest, "a first automatic-output frame")
        release = _hold_reader(sensor.port)
        with pytest.raises(DeviceTimeout):
            # answered on the line, but the held reader does not see it
            await sensor.read_temperature()
        await dev.stage.move_to_deg(4.0, -3.0)  # frames of the motion queue up behind that answer
        await dev.stage.wait_until_idle(60)
        await at_rest(stage_sim)
        truth = stage_sim.world.sample(noisy=False)
        # the answer to the mark's own request leaves late, after the reader is let go: the old
        # answer is then the only one the reader has parsed when the request is resolved
        stage_sim.faults("reference_sensor").slow(0.3)
        called_s = sensor.clock.monotonic()
        threading.Timer(0.2, release.set).start()
        mark = await sensor.sync()
        await eventually_async(
            lambda: len(sensor.readings_after(mark)) >= 5, "five readings after the mark"
        )
        assert any(
            abs(r.x_deg - truth["ref_x_deg"]) > 0.5 for r in sensor.readings_after(called_s)
        ), "the held reader delivered no reading of the motion after the call: nothing was tested"
        fresh = sensor.readings_after(mark)
        off = [
            r
            for r in fresh
            if abs(r.x_deg - truth["ref_x_deg"]) > NOISE_TOL_DEG
            or abs(r.y_deg - truth["ref_y_deg"]) > NOISE_TOL_DEG
        ]
        assert not off, (
            f"{len(off)} of {len(fresh)} readings after the mark are not of the new pose",
            off[:3],
            truth,
        )
        assert not sensor.temp_answer_owed

    run_with_devices(stage_sim, body)


def test_an_instrument_without_a_temperature_answer_still_gives_a_mark(stage_sim, monkeypatch):
    """A family (A) firmware that ignores 0x06: after SYNC_ASKS requests the mark falls back to the
    present time, and the firmware is not asked again."""

    async def body(dev):
        sensor = dev.reference_sensor
        await eventually_async(sensor.latest, "a first automatic-output frame")
        firmware = stage_sim.ports["reference_sensor"].firmware
        answer, asked = firmware._answer, []

        def no_temperature(req):
            if req.command == 0x06:
                asked.append(req)
                return None
            return answer(req)

        monkeypatch.setattr(firmware, "_answer", no_temperature)
        called_s = sensor.clock.monotonic()
        mark = await sensor.sync()
        assert mark >= called_s and not sensor.answers_temperature and len(asked) == SYNC_ASKS
        again = await sensor.sync()
        assert again >= mark and len(asked) == SYNC_ASKS  # not asked again

    run_with_devices(stage_sim, body)


def test_a_lost_temperature_answer_is_asked_again(stage_sim):
    """One answer lost on the line (here: sent from a wrong address, so the driver may not take it)
    costs a second request, not the temperature and not the mark."""

    async def body(dev):
        sensor = dev.reference_sensor
        await eventually_async(sensor.latest, "a first automatic-output frame")
        stage_sim.faults("reference_sensor").wrong_address(1)
        called_s = sensor.clock.monotonic()
        mark = await sensor.sync()
        assert mark > called_s and sensor.answers_temperature
        assert sensor.status.counters.timeouts == 1 and sensor.status.counters.wrong_address == 1
        assert sensor.temp_c == pytest.approx(stage_sim.world.temp_c(), abs=0.05)

    run_with_devices(stage_sim, body)


def test_a_reader_held_past_one_timeout_still_gives_a_mark(stage_sim):
    """The reader held up for longer than one request's timeout (a loaded machine): nothing at all
    arrives during the first request, which is not taken for a silent instrument."""

    async def body(dev):
        sensor = dev.reference_sensor
        await eventually_async(sensor.latest, "a first automatic-output frame")
        release = _hold_reader(sensor.port)
        threading.Timer(sensor.timeout_s * 1.5, release.set).start()
        called_s = sensor.clock.monotonic()
        mark = await sensor.sync()
        assert mark > called_s and sensor.answers_temperature
        assert sensor.status.counters.timeouts >= 1  # the first request did go unanswered in time
        assert sensor.temp_c == pytest.approx(stage_sim.world.temp_c(), abs=0.05)

    run_with_devices(stage_sim, body)


def test_a_silent_instrument_fails_the_mark_naming_role_and_port(stage_sim):
    async def body(dev):
        sensor = dev.reference_sensor
        await eventually_async(sensor.latest, "a first automatic-output frame")
        stage_sim.faults("reference_sensor").silence(True)
        # the in-memory line says what is still on its way
        line = stage_sim.ports["reference_sensor"].line
        await eventually_async(
            lambda: line.pending_for_host() == 0, "the frames sent before the silence arrived"
        )
        with pytest.raises(
            DeviceTimeout, match="reference_sensor.*" + re.escape(sensor.port.where)
        ):
            await sensor.sync()
        assert sensor.answers_temperature  # silence is not taken for a firmware without 0x06

    run_with_devices(stage_sim, body)
