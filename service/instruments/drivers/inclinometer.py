"""Family (A) drivers: the biaxial binary inclinometers (reference and measurement sensor) and the
triaxial module, packed BCD degrees and sines on the wire, automatic output between answers."""

from __future__ import annotations

import contextlib
import datetime as dt
from collections.abc import Callable
from typing import Any

from service.clock import Clock
from service.instruments import binary
from service.instruments.base import (
    DeviceIdentity,
    Reading,
    TemperatureOnRequest,
    TiltSensor,
    TriaxialSensor,
)
from service.instruments.drivers.common import SerialDriver, present
from service.instruments.transport import DeviceError, DeviceRefused, DeviceTimeout, SerialPort

SYNC_ASKS = 3  # temperature requests a sync mark makes before it takes the firmware to lack 0x06


class BinaryInclinometer(SerialDriver, TiltSensor, TemperatureOnRequest):
    """reference_sensor / measurement_sensor (family A). Automatic output keeps `latest()` fresh."""

    protocol = "binary"
    # packed BCD with four decimals of a degree: an uncertainty budget's resolution
    resolution_deg = 1e-4

    def __init__(
        self,
        role: str,
        port: SerialPort,
        clock: Clock,
        timeout_s: float,
        address: int,
        output_rate_hz: int | str = 0,
    ) -> None:
        super().__init__(role, port, clock, timeout_s)
        self.address = address
        self.output_rate_hz = output_rate_hz
        # The last temperature answered (0x06): angle frames carry none, so readings carry this one.
        self.temp_c: float | None = None
        # bench time its answer was parsed: a mark in the stream
        self.temp_answered_s: float | None = None
        self.answers_temperature = True  # until an instrument of the family is found that does not
        # A temperature request timed out: its answer may still come, and be taken for the next
        # request's (answers carry no sequence number).
        self.temp_answer_owed = False
        port.own(address)
        port.add_listener(self._on_message)

    def _stamp(self, **fields: Any) -> Reading:
        return super()._stamp(temp_c=self.temp_c, **fields)

    def _on_message(self, msg: object, _utc: dt.datetime) -> None:
        # the reader thread, in the order the bytes came: stamps here order answers and automatic
        # output
        if isinstance(msg, binary.BinaryAnswer) and msg.address == self.address:
            if msg.command == binary.READ_XY | binary.ANSWER:
                self._latest = self._stamp(x_deg=msg.x_deg, y_deg=msg.y_deg)
            elif msg.command == binary.READ_SINES | binary.ANSWER and msg.sines is not None:
                sx, sy, sz = msg.sines
                self._latest = self._stamp(sx=sx, sy=sy, sz=sz)
            elif msg.command == binary.READ_TEMP | binary.ANSWER and msg.temp_c is not None:
                self.temp_c = float(msg.temp_c)
                self.temp_answered_s = self.clock.monotonic()

    def _match(self, command: int) -> Callable[[Any], bool]:
        return lambda m: (
            isinstance(m, binary.BinaryAnswer)
            and m.address == self.address
            and m.command == command
        )

    async def _command(self, command: int, argument: int | None, what: str) -> binary.BinaryAnswer:
        req = binary.encode_request(binary.BinaryRequest(self.address, command, argument))
        answer: binary.BinaryAnswer = await self._ask(
            req, self._match(command | binary.ANSWER), what
        )
        return answer

    async def _status_command(self, command: int, argument: int, what: str) -> None:
        ans = await self._command(command, argument, what)
        if ans.status != binary.STATUS_DONE:
            raise DeviceRefused(
                f"{self.role}: {what} refused by the instrument on {self.port.where}"
            )

    async def start(self) -> None:
        await super().start()
        await self.configure_output()

    async def configure_output(self) -> None:
        """Set the automatic output the role asks for (after power-up or a reconnect)."""
        rate = self.output_rate_hz
        code = (
            0x07
            if rate == "continuous"
            else next(
                mode_code
                for mode_code, mode_rate in binary.OUTPUT_MODES.items()
                if mode_rate == rate
            )
        )
        if self.port.wait_connected(0):
            with contextlib.suppress(DeviceError):
                await self._status_command(binary.SET_OUTPUT, code, "set automatic output")

    async def identify(self) -> DeviceIdentity:
        """Family (A) has no identification command: a read at the address proves the instrument is
        there."""
        await self.read_tilt()
        self.identity = DeviceIdentity(
            model="0x68 binary inclinometer",
            serial=self.port.usb_serial,
            address=f"0x{self.address:02X}",
        )
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
        self.temp_c = float(present(ans.temp_c, "read temperature"))
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
                    # set by the reader before the answer is handed over
                    assert self.temp_answered_s is not None
                    return self.temp_answered_s
            if not angles_came:
                raise DeviceTimeout(
                    f"{self.role}: neither a temperature answer nor an angle frame on "
                    f"{self.port.where} through {SYNC_ASKS} requests of {self.timeout_s:g} s"
                )
            self.answers_temperature = False
        return self.clock.monotonic()

    async def set_relative_zero(self) -> None:
        await self._status_command(binary.SET_ZERO, binary.ZERO_RELATIVE, "set relative zero")

    async def set_absolute_zero(self) -> None:
        await self._status_command(binary.SET_ZERO, binary.ZERO_ABSOLUTE, "set absolute zero")


class TriaxialModule(BinaryInclinometer, TriaxialSensor):
    """triaxial_sensor: family (A) with command 0x07, sines in g."""

    async def identify(self) -> DeviceIdentity:
        await self.read_sines()
        self.identity = DeviceIdentity(
            model="0x68 triaxial module",
            serial=self.port.usb_serial,
            address=f"0x{self.address:02X}",
        )
        return self.identity

    async def read_sines(self) -> Reading:
        ans = await self._command(binary.READ_SINES, None, "read sines")
        sx, sy, sz = present(ans.sines, "read sines")
        return self._stamp(sx=sx, sy=sy, sz=sz)  # kept by the reader's listener already
