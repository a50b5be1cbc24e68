"""Every injected fault, on every family, through real pseudo-terminals: survived, counted,
reported, and never a value from a damaged frame."""

from __future__ import annotations

import asyncio

import pytest

from service.instruments.transport import DeviceError, DeviceTimeout, DeviceUnavailable
from tests.helpers.instruments import eventually_async, run_with_devices

# role -> (a read returning a value to compare, a function of the reading giving that value)
STAGE_ROLES = ["reference_sensor", "stage", "adc_sensor"]
ROTARY_ROLES = ["triaxial_sensor", "turntable_sensor", "rotary_table"]


def _reader(dev, role):
    d = dev[role]
    if role in ("reference_sensor", "measurement_sensor", "turntable_sensor"):
        return d.read_tilt
    if role == "triaxial_sensor":
        return d.read_sines
    if role == "adc_sensor":
        return lambda: d.read_counts(1)
    if role == "stage":
        return d.x.position_pulses
    return d.position_pulses


def _driver(dev, role):
    return dev[role].x if role == "stage" else dev[role]


async def _line_to_ourselves(dev, role):
    """No automatic output and no polling: the next frame on the line is the answer to our
    request."""
    d = _driver(dev, role)
    await d.stop_polling()
    if hasattr(d, "output_rate_hz"):
        d.output_rate_hz = 0
        await d.configure_output()
    await _reader(dev, role)()
    return d


def _valid(role, value, sim) -> bool:
    """A value that could have come from the instrument (never one built from damaged bytes)."""
    if role in ("stage", "rotary_table"):
        return value == 0
    if role == "adc_sensor":
        return 0 <= value.counts <= 4095
    if role == "triaxial_sensor":
        truth = sim.world.sines(noisy=False)
        return all(abs(a - b) < 0.01 for a, b in zip((value.sx, value.sy, value.sz), truth))
    if role == "turntable_sensor":
        return value.status == 0 and abs(value.x_deg) < 0.1 and abs(value.y_deg) < 0.1
    truth = sim.world.sample(noisy=False)
    return (
        abs(value.x_deg - truth["ref_x_deg"]) < 0.02
        and abs(value.y_deg - truth["ref_y_deg"]) < 0.02
    )


async def _read_through(dev, role, sim, tries: int = 6):
    """Read until an answer comes; every answer that comes must be valid."""
    read = _reader(dev, role)
    last = None
    for _ in range(tries):
        try:
            value = await read()
        except DeviceError as exc:
            last = exc
            continue
        assert _valid(role, value, sim), f"{role}: a value from damaged bytes: {value!r}"
        return value
    raise AssertionError(f"{role}: no good answer after {tries} tries ({last})")


def _bench(request, role):
    return request.getfixturevalue("stage_sim" if role in STAGE_ROLES else "rotary_sim")


@pytest.mark.parametrize("role", STAGE_ROLES + ROTARY_ROLES)
def test_garbage_on_the_line_is_skipped_and_counted(request, role):
    sim = _bench(request, role)

    async def body(dev):
        await _read_through(dev, role, sim)
        c = _driver(dev, role).status.counters
        before = c.resyncs + c.bad_checksum
        sim.faults(role).garbage(64, seed=7)
        # a streaming sensor's read may answer with a frame that came before the garbage: read on
        # until the driver has met it (it is on the line, so it comes), every answer meanwhile valid
        for _ in range(20):
            await _read_through(dev, role, sim)
            c = _driver(dev, role).status.counters
            if c.resyncs + c.bad_checksum > before:
                break
        assert c.resyncs + c.bad_checksum > before, c

    run_with_devices(sim, body)


@pytest.mark.parametrize("role", STAGE_ROLES + ROTARY_ROLES)
def test_dropped_bytes_lose_an_answer_never_a_value(request, role):
    sim = _bench(request, role)

    async def body(dev):
        await _read_through(dev, role, sim)
        d = await _line_to_ourselves(dev, role)
        for n in (1, 3):
            sim.faults(role).drop_bytes(n)
            await _read_through(dev, role, sim)
        c = d.status.counters
        assert c.bad_checksum + c.resyncs + c.timeouts > 0

    run_with_devices(sim, body)


@pytest.mark.parametrize("role", ["reference_sensor", "triaxial_sensor", "turntable_sensor"])
def test_corrupted_checksum_is_counted_and_the_value_dropped(request, role):
    sim = _bench(request, role)

    async def body(dev):
        d = await _line_to_ourselves(dev, role)
        d.port.decoder.stats.bad_checksum = 0
        sim.faults(role).corrupt_checksum()
        with pytest.raises(DeviceTimeout):
            await _reader(dev, role)()
        assert d.status.counters.bad_checksum == 1 and d.status.counters.timeouts == 1
        await _read_through(dev, role, sim)

    run_with_devices(sim, body)


@pytest.mark.parametrize("role", ["stage", "adc_sensor"])
def test_families_without_checksum_refuse_the_checksum_fault(request, role):
    with pytest.raises(ValueError, match="no checksum"):
        _bench(request, role).faults(role).corrupt_checksum()


@pytest.mark.parametrize(
    "role", ["reference_sensor", "stage", "adc_sensor", "turntable_sensor", "rotary_table"]
)
def test_slow_answers_within_and_beyond_the_timeout(request, role):
    sim = _bench(request, role)

    async def body(dev):
        d = await _line_to_ourselves(dev, role)
        sim.faults(role).slow(d.timeout_s / 5)
        await _read_through(dev, role, sim, tries=1)  # late but in time
        sim.faults(role).slow(d.timeout_s * 3)
        with pytest.raises(DeviceTimeout, match=role):
            await _reader(dev, role)()
        assert d.status.counters.timeouts == 1
        await _read_through(dev, role, sim)

    run_with_devices(sim, body)


@pytest.mark.parametrize(
    "role", ["reference_sensor", "stage", "turntable_sensor", "triaxial_sensor"]
)
def test_an_answer_from_the_wrong_address_is_not_taken(request, role):
    sim = _bench(request, role)

    async def body(dev):
        d = await _line_to_ourselves(dev, role)
        sim.faults(role).wrong_address()
        with pytest.raises(DeviceTimeout):
            await _reader(dev, role)()
        assert d.status.counters.wrong_address == 1
        await _read_through(dev, role, sim)

    run_with_devices(sim, body)


def test_the_adc_has_no_address_to_fake(stage_sim):
    with pytest.raises(ValueError, match="no address"):
        stage_sim.faults("adc_sensor").wrong_address()


# a pulled USB adapter: the pty goes away under the open port (every device on a pty)
@pytest.mark.pty
@pytest.mark.parametrize("role", STAGE_ROLES + ROTARY_ROLES)
def test_a_pulled_cable_is_reported_and_the_port_reopened(request, role):
    sim = _bench(request, role)

    async def body(dev):
        await _read_through(dev, role, sim)
        d = _driver(dev, role)
        sim.faults(role).disconnect(0.3)
        await eventually_async(lambda: d.status.state == "reconnecting", "the outage shown")
        with pytest.raises(DeviceError):
            await _reader(dev, role)()
        await eventually_async(
            lambda: d.status.state == "connected", "the port reopened", attempts=500
        )
        assert d.status.counters.reconnects == 1
        await _read_through(dev, role, sim)

    run_with_devices(sim, body)


# a pulled USB adapter: the pty goes away under the open port (every device on a pty)
@pytest.mark.pty
@pytest.mark.parametrize("role", ["reference_sensor", "stage", "turntable_sensor"])
def test_a_cable_pulled_in_the_middle_of_a_read_fails_that_read_not_by_timeout(request, role):
    sim = _bench(request, role)

    async def body(dev):
        d = await _line_to_ourselves(dev, role)
        d.timeout_s = 30.0  # the read would wait this long if the outage were not noticed
        sim.faults(role).slow(20.0)  # the answer is on its way when the cable goes
        read = asyncio.ensure_future(_reader(dev, role)())
        await eventually_async(
            lambda: not sim.faults(role).slow_next, "the request reached the instrument"
        )
        sim.faults(role).disconnect(0.3)
        with pytest.raises(DeviceUnavailable, match="went away"):
            await read
        d.timeout_s = 0.5
        await eventually_async(
            lambda: d.status.state == "connected", "the port reopened", attempts=500
        )
        await _read_through(dev, role, sim)

    run_with_devices(sim, body)


def test_a_silent_instrument_times_out_and_says_where(stage_sim):
    async def body(dev):
        await _line_to_ourselves(dev, "reference_sensor")
        stage_sim.faults("reference_sensor").silence()
        with pytest.raises(
            DeviceTimeout, match=r"reference_sensor: read tilt: no answer on .*reference_sensor"
        ):
            await dev.reference_sensor.read_tilt()
        stage_sim.faults("reference_sensor").silence(False)
        await _read_through(dev, "reference_sensor", stage_sim)

    run_with_devices(stage_sim, body)
