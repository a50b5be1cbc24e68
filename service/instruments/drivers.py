"""Drivers per role: the lab's operations in the lab's units, over one family's bytes.

Units are converted here and nowhere else: packed BCD degrees, milliradians and pulses come
in, degrees leave. A driver never knows whether a simulator or an instrument answers.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import datetime as dt
import math
from dataclasses import replace
from typing import Any

from service.clock import Clock
from service.instruments import adc, binary, controller, rs485
from service.instruments.base import AxisState, DeviceCounters, DeviceIdentity, DeviceStatus, Reading
from service.instruments.transport import DeviceError, DeviceRefused, DeviceTimeout, SerialPort


def _present(value: Any, what: str) -> Any:
    """A field the answer must carry; an answer without it is the instrument's error, said as one."""
    if value is None:
        raise DeviceError(f"{what}: the answer lacks its value")
    return value


IDLE_POLL_MISSES = 3  # unanswered state queries in a row before waiting for a move gives up
SYNC_ASKS = 3  # temperature requests a sync mark makes before it takes the firmware to lack 0x06
RECENT_READINGS = 4096  # per driver: over 8 s of a sped-up bench's continuous output


class _Driver:
    """What every driver shares: its port, its counters, its identity and latest reading."""

    protocol = ""

    def __init__(self, role: str, port: SerialPort, clock: Clock, timeout_s: float) -> None:
        self.role = role
        self.port = port
        self.clock = clock
        self.timeout_s = timeout_s
        self.identity: DeviceIdentity | None = None
        self.timeouts = 0
        # Every reading, not only the latest: waiting for settled readings must not depend on how
        # often the waiting side looks (a sped-up bench sends hundreds a second).
        self.recent: collections.deque[Reading] = collections.deque(maxlen=RECENT_READINGS)
        self._last: Reading | None = None
        self._poll_task: asyncio.Task | None = None
        self._poll_read = None  # the read a polling driver repeats

    @property
    def _latest(self) -> Reading | None:
        return self._last

    @_latest.setter
    def _latest(self, reading: Reading | None) -> None:
        self._last = reading
        if reading is not None:
            self.recent.append(reading)

    def readings_after(self, bench_s: float) -> list[Reading]:
        """The readings kept that are stamped after `bench_s` (bench seconds), oldest first."""
        kept = list(self.recent)  # one C call under the GIL: safe against the reader thread appending
        return [r for r in kept if r.bench_s > bench_s]

    @property
    def status(self) -> DeviceStatus:
        st = self.port.decoder.stats
        return DeviceStatus(
            role=self.role, port=self.port.where, protocol=self.protocol, state=self.port.state,
            last_frame_utc=self.port.last_frame_utc,
            counters=DeviceCounters(frames=st.frames, bad_checksum=st.bad_checksum, resyncs=st.resyncs,
                                    timeouts=self.timeouts, reconnects=self.port.reconnects,
                                    wrong_address=self.port.wrong_address),
            identity=self.identity, error=self.port.error)

    def latest(self) -> Reading | None:
        return self._latest

    async def sync(self) -> float:
        """A mark in the reading stream (bench seconds): every reading stamped after it was produced
        after this call. Readings are stamped when they are parsed, so a reader that lags (a loaded
        machine, a sped-up bench) hands out, after a move, readings the instrument made during it;
        a caller that needs readings of the present pose counts only those after the mark.

        A polling driver reads once more: requests on a port go one at a time, so every reading
        stamped after this one was asked for after it. A driver that reads only when asked: the
        present time (nothing older can arrive later).
        """
        if self._poll_read is not None and self._poll_task is not None:
            return float((await self._poll_read()).bench_s)
        return self.clock.monotonic()

    def _stamp(self, **fields: Any) -> Reading:
        return Reading(role=self.role, bench_s=self.clock.monotonic(), time_utc=dt.datetime.now(dt.UTC), **fields)

    async def _ask(self, data: bytes, match, what: str):
        try:
            return await self.port.request(data, match, self.timeout_s, f"{self.role}: {what}")
        except DeviceTimeout:
            self.timeouts += 1
            raise

    async def start(self) -> None:
        """Start the port's reader and give it a moment to open; a port that does not open keeps trying."""
        self.port.start()
        await asyncio.to_thread(self.port.wait_connected, self.timeout_s * 4)

    async def stop_polling(self) -> None:
        """No more reads of its own (a caller that wants the line to itself, as a probe or a test)."""
        task, self._poll_task = self._poll_task, None
        if task is None:
            return
        while not task.done():
            task.cancel()
            await asyncio.wait({task}, timeout=0.1)
        with contextlib.suppress(asyncio.CancelledError, Exception):
            task.result()

    async def close(self) -> None:
        await self.stop_polling()
        self.port.stop()

    def _start_polling(self, rate_hz: float, read) -> None:
        self._poll_read = read

        async def poll() -> None:
            while self._poll_task is not None:
                with contextlib.suppress(DeviceError):
                    await read()
                await self.clock.sleep(1.0 / rate_hz)  # bench time: a sped-up bench is polled faster too

        self._poll_task = asyncio.get_running_loop().create_task(poll())


class BinaryInclinometer(_Driver):
    """reference_sensor / measurement_sensor (family A). Automatic output keeps `latest()` fresh."""

    protocol = "binary"
    resolution_deg = 1e-4  # packed BCD with four decimals of a degree: an uncertainty budget's resolution

    def __init__(self, role, port, clock, timeout_s, address: int, output_rate_hz: int | str = 0) -> None:
        super().__init__(role, port, clock, timeout_s)
        self.address = address
        self.output_rate_hz = output_rate_hz
        # The last temperature answered (0x06): angle frames carry none, so readings carry this one.
        self.temp_c: float | None = None
        self.temp_answered_s: float | None = None  # bench time its answer was parsed: a mark in the stream
        self.answers_temperature = True  # until an instrument of the family is found that does not
        # A temperature request timed out: its answer may still come, and be taken for the next
        # request's (answers carry no sequence number).
        self.temp_answer_owed = False
        port.own(address)
        port.add_listener(self._on_message)

    def _stamp(self, **fields: Any) -> Reading:
        return super()._stamp(temp_c=self.temp_c, **fields)

    def _on_message(self, msg, _utc) -> None:
        # the reader thread, in the order the bytes came: stamps here order answers and automatic output
        if isinstance(msg, binary.BinaryAnswer) and msg.address == self.address:
            if msg.command == binary.READ_XY | binary.ANSWER:
                self._latest = self._stamp(x_deg=msg.x_deg, y_deg=msg.y_deg)
            elif msg.command == binary.READ_SINES | binary.ANSWER and msg.sines is not None:
                sx, sy, sz = msg.sines
                self._latest = self._stamp(sx=sx, sy=sy, sz=sz)
            elif msg.command == binary.READ_TEMP | binary.ANSWER and msg.temp_c is not None:
                self.temp_c = float(msg.temp_c)
                self.temp_answered_s = self.clock.monotonic()

    def _match(self, command: int):
        return lambda m: isinstance(m, binary.BinaryAnswer) and m.address == self.address and m.command == command

    async def _command(self, command: int, argument: int | None, what: str) -> binary.BinaryAnswer:
        req = binary.encode_request(binary.BinaryRequest(self.address, command, argument))
        return await self._ask(req, self._match(command | binary.ANSWER), what)

    async def _status_command(self, command: int, argument: int, what: str) -> None:
        ans = await self._command(command, argument, what)
        if ans.status != binary.STATUS_DONE:
            raise DeviceRefused(f"{self.role}: {what} refused by the instrument on {self.port.where}")

    async def start(self) -> None:
        await super().start()
        await self.configure_output()

    async def configure_output(self) -> None:
        """Set the automatic output the role asks for (after power-up or a reconnect)."""
        rate = self.output_rate_hz
        code = 0x07 if rate == "continuous" else next(c for c, r in binary.OUTPUT_MODES.items() if r == rate)
        if self.port.wait_connected(0):
            with contextlib.suppress(DeviceError):
                await self._status_command(binary.SET_OUTPUT, code, "set automatic output")

    async def identify(self) -> DeviceIdentity:
        """Family (A) has no identification command: a read at the address proves the instrument is there."""
        await self.read_tilt()
        self.identity = DeviceIdentity(model="0x68 binary inclinometer", serial=self.port.usb_serial or
                                       f"address 0x{self.address:02X} on {self.port.where}")
        return self.identity

    async def read_tilt(self) -> Reading:
        ans = await self._command(binary.READ_XY, None, "read tilt")
        # the reader's listener has kept this answer already (an 0x84 is an 0x84): not a second time
        return self._stamp(x_deg=ans.x_deg, y_deg=ans.y_deg)

    async def read_temperature(self) -> float:
        try:
            ans = await self._command(binary.READ_TEMP, None, "read temperature")
        except DeviceTimeout:
            self.temp_answer_owed = True
            raise
        self.temp_answer_owed = False
        self.temp_c = float(_present(ans.temp_c, "read temperature"))
        return self.temp_c

    async def sync(self) -> float:
        """Ask the temperature: the instrument answers between its automatic frames, so the answer
        marks the stream (and the readings after it carry a temperature of the present).

        An answer lost on the line (a damaged frame) is asked again; an instrument that lets
        SYNC_ASKS requests in a row go unanswered while its angles keep coming is taken for a
        firmware without 0x06, and is not asked again. One that sends nothing at all through
        those requests is not answering (a single silent request may be a loaded machine's reader
        held up, not the instrument).
        """
        if self.answers_temperature:
            # An answer owed from before the call may be taken for the first request's; it was made
            # before the call, so it cannot mark the stream: then the second answer does.
            answers_needed = 2 if self.temp_answer_owed else 1
            angles_came = False
            for _ in range(SYNC_ASKS + answers_needed - 1):
                asked_s = self.clock.monotonic()
                try:
                    await self.read_temperature()
                except DeviceTimeout:
                    last = self._latest
                    angles_came = angles_came or (last is not None and last.bench_s > asked_s)
                    continue
                answers_needed -= 1
                if answers_needed == 0:
                    assert self.temp_answered_s is not None  # set by the reader before the answer is handed over
                    return self.temp_answered_s
            if not angles_came:
                raise DeviceTimeout(f"{self.role}: neither a temperature answer nor an angle frame on "
                                    f"{self.port.where} through {SYNC_ASKS} requests of {self.timeout_s:g} s")
            self.answers_temperature = False
        return self.clock.monotonic()

    async def set_relative_zero(self) -> None:
        await self._status_command(binary.SET_ZERO, binary.ZERO_RELATIVE, "set relative zero")

    async def set_absolute_zero(self) -> None:
        await self._status_command(binary.SET_ZERO, binary.ZERO_ABSOLUTE, "set absolute zero")


class TriaxialModule(BinaryInclinometer):
    """triaxial_sensor: family (A) with command 0x07, sines in g."""

    async def identify(self) -> DeviceIdentity:
        await self.read_sines()
        self.identity = DeviceIdentity(model="0x68 triaxial module", serial=self.port.usb_serial or
                                       f"address 0x{self.address:02X} on {self.port.where}")
        return self.identity

    async def read_sines(self) -> Reading:
        ans = await self._command(binary.READ_SINES, None, "read sines")
        sx, sy, sz = _present(ans.sines, "read sines")
        return self._stamp(sx=sx, sy=sy, sz=sz)  # kept by the reader's listener already


class Rs485Inclinometer(_Driver):
    """turntable_sensor (family B): one address on a bus that other instruments may share."""

    protocol = "rs485"
    resolution_deg = 1e-6 * 180.0 / math.pi  # milliradians with three decimals: 1 µrad

    def __init__(self, role, port, clock, timeout_s, address: int, poll_rate_hz: float | None = None) -> None:
        super().__init__(role, port, clock, timeout_s)
        self.address = address
        self.poll_rate_hz = poll_rate_hz
        port.own(address)

    def _match(self, kind, **fields):
        def match(m):
            return isinstance(m, kind) and m.address == self.address and all(getattr(m, k) == v for k, v in fields.items())
        return match

    async def start(self) -> None:
        await super().start()
        if self.poll_rate_hz:
            self._start_polling(self.poll_rate_hz, self.read_tilt)

    async def read_tilt(self) -> Reading:
        req = rs485.encode_request(rs485.Rs485Request(self.address, "RD"))
        ans = await self._ask(req, self._match(rs485.Rs485Reading), "read tilt")
        self._latest = self._stamp(x_deg=rs485.mrad_to_deg(ans.x_mrad), y_deg=rs485.mrad_to_deg(ans.y_mrad),
                                   temp_c=ans.temp_c, status=ans.status)
        return self._latest

    async def read_temperature(self) -> float:
        return float(_present((await self.read_tilt()).temp_c, "read temperature"))

    async def _zero(self, relative: bool) -> None:
        req = rs485.encode_request(rs485.Rs485Request(self.address, "ZR" if relative else "ZA"))
        await self._ask(req, self._match(rs485.Rs485ZeroDone, relative=relative),
                        "set relative zero" if relative else "set absolute zero")

    async def set_relative_zero(self) -> None:
        await self._zero(True)

    async def set_absolute_zero(self) -> None:
        await self._zero(False)

    async def identify(self) -> DeviceIdentity:
        req = rs485.encode_request(rs485.Rs485Request(self.address, "ID"))
        ans = await self._ask(req, self._match(rs485.Rs485Identity), "identify")
        self.identity = DeviceIdentity(model=ans.model, serial=ans.serial, firmware=ans.firmware)
        return self.identity


class AdcSensor(_Driver):
    """adc_sensor (family C): counts of the 12-bit ADC, a mean of n conversions per reading."""

    protocol = "adc"

    def __init__(self, role, port, clock, timeout_s, conversions: int = 1, poll_rate_hz: float | None = None) -> None:
        super().__init__(role, port, clock, timeout_s)
        self.conversions = conversions
        self.poll_rate_hz = poll_rate_hz

    async def start(self) -> None:
        await super().start()
        if self.poll_rate_hz:
            self._start_polling(self.poll_rate_hz, lambda: self.read_counts(self.conversions))

    async def read_counts(self, conversions: int = 1) -> Reading:
        n = None if conversions == 1 else conversions
        req = adc.encode_request(adc.AdcRequest(n))
        ans = await self._ask(req, lambda m: isinstance(m, adc.AdcCounts) and m.conversions == n, "read counts")
        self._latest = self._stamp(counts=ans.counts)
        return self._latest

    async def identify(self) -> DeviceIdentity:
        ans = await self._ask(adc.encode_request(adc.AdcRequest(identify=True)),
                              lambda m: isinstance(m, adc.AdcIdentity), "identify")
        self.identity = DeviceIdentity(model=ans.model, serial=ans.serial)
        return self.identity


class ControllerAxis(_Driver):
    """One axis of a family (D) controller, in pulses on the wire and degrees for callers."""

    protocol = "controller"

    def __init__(self, role, port, clock, timeout_s, axis: int, pulse_deg: float,
                 velocity_pulses_per_s: int | None = None,
                 soft_limits_deg: tuple[float, float] | None = None) -> None:
        super().__init__(role, port, clock, timeout_s)
        self.axis = axis
        self.pulse_deg = pulse_deg
        port.own(axis)
        self.velocity_pulses_per_s = velocity_pulses_per_s
        self.soft_limits_deg = soft_limits_deg

    async def start(self) -> None:
        await super().start()
        if self.port.wait_connected(0):
            with contextlib.suppress(DeviceError):
                await self.configure()

    async def configure(self) -> None:
        """Velocity and soft limits from the bench configuration."""
        if self.velocity_pulses_per_s is not None:
            await self._send("VA", self.velocity_pulses_per_s)
        if self.soft_limits_deg is not None:
            lo, hi = (round(v / self.pulse_deg) for v in self.soft_limits_deg)
            await self._send("SL", lo)
            await self._send("SR", hi)

    async def _send(self, command: str, value: int | None = None) -> None:
        await self.port.send(controller.encode_command(controller.ControllerCommand(self.axis, command, value)))

    async def _query(self, command: str) -> controller.ControllerAnswer:
        req = controller.encode_command(controller.ControllerCommand(self.axis, command, query=True))
        return await self._ask(req, lambda m: isinstance(m, controller.ControllerAnswer) and m.axis == self.axis
                               and m.command == command, f"axis {self.axis} {command}?")

    async def _checked(self, command: str, value: int | None, what: str) -> None:
        """Send a command the controller does not answer, then ask its error code: refusals raise."""
        await self._send(command, value)
        code = (await self._query("TE")).value
        if code:
            raise DeviceRefused(f"{self.role}: axis {self.axis} {what}: "
                                f"{controller.ERROR_NAMES.get(code, f'error {code}')}")

    async def identify(self) -> DeviceIdentity:
        ans = await self._query("ID")
        model, _, serial = str(_present(ans.text, "identify")).partition(" ")
        self.identity = DeviceIdentity(model=model, serial=serial)
        return self.identity

    async def move_to_pulses(self, pulses: int) -> None:
        await self._checked("PA", int(pulses), f"move to {int(pulses)} pulses")

    async def move_by_pulses(self, pulses: int) -> None:
        await self._checked("PR", int(pulses), f"move by {int(pulses)} pulses")

    async def move_to_deg(self, angle_deg: float) -> int:
        pulses = round(angle_deg / self.pulse_deg)
        await self.move_to_pulses(pulses)
        return pulses

    async def position_pulses(self) -> int:
        return int(_present((await self._query("TP")).value, "query TP"))

    async def position_deg(self) -> float:
        return await self.position_pulses() * self.pulse_deg

    async def velocity_pulses(self) -> int:
        return int(_present((await self._query("VA")).value, "query VA"))

    async def soft_limits_pulses(self) -> tuple[int, int]:
        return (int(_present((await self._query("SL")).value, "query SL")),
                int(_present((await self._query("SR")).value, "query SR")))

    async def last_error(self) -> int:
        return int(_present((await self._query("TE")).value, "query TE"))

    async def state(self) -> AxisState:
        code = int(_present((await self._query("TS")).value, "query TS"))
        return controller.STATE_NAMES.get(code, "error")  # type: ignore[return-value]

    async def wait_until_idle(self, timeout_s: float, poll_s: float = 0.05) -> None:
        """Poll the state until ready. A state query left unanswered (an answer lost on the line) is
        polled again; IDLE_POLL_MISSES of them in a row raise."""
        deadline = self.clock.monotonic() + timeout_s
        misses = 0
        while True:
            try:
                s = await self.state()
            except DeviceTimeout:
                misses += 1
                if misses >= IDLE_POLL_MISSES or self.clock.monotonic() > deadline:
                    raise
                continue
            misses = 0
            if s == "ready":
                return
            if s in ("hard_limit", "error"):
                code = await self.last_error()
                raise DeviceError(f"{self.role}: axis {self.axis} stopped in state {s}"
                                  f" ({controller.ERROR_NAMES.get(code, code)})")
            if self.clock.monotonic() > deadline:
                raise DeviceTimeout(f"{self.role}: axis {self.axis} still {s} after {timeout_s:g} s")
            await self.clock.sleep(poll_s)

    async def stop(self) -> None:
        await self._send("ST")

    async def home(self) -> None:
        await self._checked("OR", None, "home")


class StageController:
    """The `stage` role: two axes of one controller, 1 upper (x) and 2 lower (y), on one port."""

    protocol = "controller"

    def __init__(self, role: str, x: ControllerAxis, y: ControllerAxis) -> None:
        self.role = role
        self.x = x
        self.y = y
        self.axes = {"x": x, "y": y}

    @property
    def status(self) -> DeviceStatus:
        s = self.x.status
        s.counters.timeouts += self.y.timeouts
        return replace(s, role=self.role)

    async def start(self) -> None:
        await self.x.start()
        await self.y.start()

    async def close(self) -> None:
        await self.y.close()
        await self.x.close()

    async def identify(self) -> DeviceIdentity:
        ident = await self.x.identify()
        self.y.identity = ident
        return ident

    async def move_to_deg(self, x_deg: float, y_deg: float) -> tuple[int, int]:
        """Start both axes; returns the pulses commanded."""
        return await self.x.move_to_deg(x_deg), await self.y.move_to_deg(y_deg)

    async def position_deg(self) -> tuple[float, float]:
        return await self.x.position_deg(), await self.y.position_deg()

    async def wait_until_idle(self, timeout_s: float) -> None:
        await asyncio.gather(self.x.wait_until_idle(timeout_s), self.y.wait_until_idle(timeout_s))

    async def stop(self) -> None:
        await self.x.stop()
        await self.y.stop()

    async def home(self) -> None:
        await self.x.home()
        await self.y.home()
