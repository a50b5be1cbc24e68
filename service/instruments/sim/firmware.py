"""Simulated firmware of each instrument family: the codec's other direction, driven by the world.

Each firmware reads requests with the same codec the drivers use (requests side), answers as
the family's instruments do (and ignores what it cannot parse), and produces automatic
output when the instrument is set to. Times of automatic output are bench time, scaled by
the clock's speed, but never faster than the line can carry at the configured baud.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from service.clock import Clock
from service.instruments import adc, binary, controller, rs485
from service.instruments.controller import Mnemonic
from service.instruments.framing import Decoder
from service.instruments.sim.world import NO_LIMIT, Axis


class AnsweringFirmware:
    """An instrument that only answers: no automatic output, and (unless a family says
    otherwise) no checksum or address a fault could spoil."""

    family = ""

    def next_due(self) -> float | None:
        return None

    def due(self, now_real: float) -> list[bytes]:
        return []

    def corrupt_checksum(self, frame: bytes) -> bytes:  # pragma: no cover - refused by Faults
        raise ValueError("no checksum")

    def readdress(self, frame: bytes) -> bytes:  # pragma: no cover - refused by Faults
        raise ValueError("no address")


class BinaryFirmware:
    """A family (A) inclinometer, or (`triaxial`) the module answering 0x07 with three sines."""

    family = "binary"

    def __init__(
        self,
        clock: Clock,
        read_xy: Callable[[float | None], tuple[float, float]],
        temp_c: Callable[[], float],
        address: int = 0,
        baud: int = 115200,
        read_sines: Callable[[], tuple[float, float, float]] | None = None,
        output_mode: int = 0,
    ) -> None:
        self.clock = clock
        self.read_xy = read_xy
        self.read_sines = read_sines
        self.temp_c = temp_c
        self.address = address
        self.baud = baud
        self.zero = (0.0, 0.0)
        self.decoder = Decoder(binary.parse_requests)
        self.output_mode = output_mode
        self._next: float | None = None
        self.auto_frames = 0
        self._set_mode(output_mode)

    # -- what the instrument measures (zero applied) --
    def _xy(self, at_s: float | None = None) -> tuple[float, float]:
        """The reading now, or (automatic output) at bench time `at_s`, the time its frame was
        due."""
        x, y = self.read_xy(at_s)
        return x - self.zero[0], y - self.zero[1]

    def _auto_frame(self, at_s: float) -> bytes:
        if self.read_sines is not None:
            return binary.encode(binary.BinaryAnswer(self.address, 0x87, sines=self.read_sines()))
        x, y = self._xy(at_s)
        return binary.encode(binary.BinaryAnswer(self.address, 0x84, x_deg=x, y_deg=y))

    def _interval_real(self) -> float | None:
        rate = binary.OUTPUT_MODES.get(self.output_mode, 0.0)
        line = binary.frame_time_s(17 if self.read_sines else 13, self.baud)
        if rate == 0.0:
            return None
        if rate is None:
            return line
        return max(self.clock.real_seconds(1.0 / rate), line)

    def _set_mode(self, mode: int) -> None:
        self.output_mode = mode
        self._next = None if self._interval_real() is None else time.monotonic()

    def handle(self, data: bytes) -> list[bytes]:
        out = []
        for req in self.decoder.feed(data):
            if not isinstance(req, binary.BinaryRequest) or req.address != self.address:
                continue
            ans = self._answer(req)
            if ans is not None:
                out.append(binary.encode(ans))
                self._after(req)
        return out

    def _answer(self, req: binary.BinaryRequest) -> binary.BinaryAnswer | None:
        address, answer_command = self.address, req.command | binary.ANSWER
        if req.command == binary.READ_SINES:
            return (
                binary.BinaryAnswer(address, answer_command, sines=self.read_sines())
                if self.read_sines
                else None
            )
        if req.command in (binary.READ_X, binary.READ_Y, binary.READ_XY):
            x, y = self._xy()
            return binary.BinaryAnswer(
                address,
                answer_command,
                x_deg=x if req.command != binary.READ_Y else None,
                y_deg=y if req.command != binary.READ_X else None,
            )
        if req.command == binary.READ_TEMP:
            return binary.BinaryAnswer(address, answer_command, temp_c=self.temp_c())
        ok = self._apply_setting(req)
        return binary.BinaryAnswer(
            address, answer_command, status=binary.STATUS_DONE if ok else binary.STATUS_REFUSED
        )

    def _apply_setting(self, req: binary.BinaryRequest) -> bool:
        """Whether the instrument takes a setting's argument; the zero and the output mode change
        at once (baud rate and address once the answer is out, in `_after`)."""
        ok = {
            binary.SET_ZERO: req.argument in (binary.ZERO_ABSOLUTE, binary.ZERO_RELATIVE),
            binary.SET_BAUD: req.argument in binary.BAUD_CODES,
            binary.SET_ADDRESS: True,
            binary.SET_OUTPUT: req.argument in binary.OUTPUT_MODES,
        }[req.command]
        if ok and req.command == binary.SET_ZERO:
            self.zero = self.read_xy(None) if req.argument == binary.ZERO_RELATIVE else (0.0, 0.0)
        if ok and req.command == binary.SET_OUTPUT and req.argument is not None:
            self._set_mode(req.argument)
        return ok

    def _after(self, req: binary.BinaryRequest) -> None:
        """Changes that apply once the answer is out."""
        if req.command == binary.SET_BAUD and req.argument in binary.BAUD_CODES:
            self.baud = binary.BAUD_CODES[req.argument]
        elif req.command == binary.SET_ADDRESS and req.argument is not None:
            self.address = req.argument

    def next_due(self) -> float | None:
        return self._next

    def due(self, now_real: float) -> list[bytes]:
        if self._next is None or now_real < self._next:
            return []
        interval = self._interval_real()
        if interval is None:
            self._next = None
            return []
        frames: list[bytes] = []
        bench_now = self.clock.monotonic()
        while self._next <= now_real and len(frames) < 64:
            # a frame sent late (a burst) still carries the reading of the time it was due
            frames.append(
                self._auto_frame(bench_now - self.clock.bench_seconds(now_real - self._next))
            )
            self._next += interval
        if self._next <= now_real:  # fell behind (a stalled process): the instrument does not burst
            self._next = now_real + interval
        self.auto_frames += len(frames)
        return frames

    def corrupt_checksum(self, frame: bytes) -> bytes:
        return frame[:-1] + bytes([frame[-1] ^ 0x5A])

    def readdress(self, frame: bytes) -> bytes:
        body = bytearray(frame)
        new = (body[2] + 1) & 0xFF
        body[-1] = (body[-1] - body[2] + new) & 0xFF
        body[2] = new
        return bytes(body)


class Rs485BusFirmware(AnsweringFirmware):
    """Several family (B) inclinometers on one bus; only the addressed one answers."""

    family = "rs485"

    def __init__(
        self,
        instruments: dict[int, Callable[[], tuple[float, float]]],
        temp_c: Callable[[], float],
        model: str = "NV-210SIM",
    ) -> None:
        self.instruments = instruments
        self.temp_c = temp_c
        self.model = model
        self.zero = {instrument: (0.0, 0.0) for instrument in instruments}
        self.decoder = Decoder(rs485.parse_requests)

    def handle(self, data: bytes) -> list[bytes]:
        out = []
        for req in self.decoder.feed(data):
            read = self.instruments.get(req.address)
            if read is None:
                continue
            address = req.address
            if req.command == "RD":
                x, y = read()
                zx, zy = self.zero[address]
                msg: rs485.Rs485Answer = rs485.Rs485Reading(
                    address, round(x - zx, 3), round(y - zy, 3), round(self.temp_c(), 2), 0
                )
            elif req.command == "ID":
                msg = rs485.Rs485Identity(address, self.model, f"SIM-B{address:02X}", "1.0")
            else:
                self.zero[address] = read() if req.command == "ZR" else (0.0, 0.0)
                msg = rs485.Rs485ZeroDone(address, req.command == "ZR")
            out.append(rs485.encode(msg))
        return out

    def corrupt_checksum(self, frame: bytes) -> bytes:
        cs = int(frame[-4:-2], 16) ^ 0x21
        return frame[:-4] + f"{cs:02X}".encode() + frame[-2:]

    def readdress(self, frame: bytes) -> bytes:
        """The same answer as if another instrument on the bus had sent it (checksum made right)."""
        text = frame.decode().rstrip("\r\n")
        payload = text[1 : text.index(" *")]
        other = (int(payload[:2], 16) + 1) & 0xFF
        payload = f"{other:02X}{payload[2:]}"
        return f"#{payload} *{rs485.checksum(payload)}\r\n".encode()


class AdcFirmware(AnsweringFirmware):
    """The 12-bit ADC in front of the analog tilt sensor (family C)."""

    family = "adc"

    def __init__(
        self, counts: Callable[[int], float], model: str = "ADC12-SIM", serial: str = "SIM-C01"
    ) -> None:
        self.counts = counts
        self.model, self.serial = model, serial
        self.decoder = Decoder(adc.parse_requests)

    def handle(self, data: bytes) -> list[bytes]:
        out = []
        for req in self.decoder.feed(data):
            if req.identify:
                out.append(adc.encode(adc.AdcIdentity(self.model, self.serial)))
            elif req.conversions is None:
                out.append(adc.encode(adc.AdcCounts(float(int(self.counts(1))))))
            else:
                mean = round(self.counts(req.conversions), 1)
                out.append(adc.encode(adc.AdcCounts(mean, req.conversions)))
        return out


class ControllerFirmware(AnsweringFirmware):
    """A family (D) controller with the world's axes (1, 2 for the stages; 3 for the rotary
    table)."""

    family = "controller"

    def __init__(
        self, axes: dict[int, Axis], model: str = "SC-200SIM", serial: str = "SIM-D01"
    ) -> None:
        self.axes = axes
        self.model, self.serial = model, serial
        self.decoder = Decoder(controller.parse_commands)

    def handle(self, data: bytes) -> list[bytes]:
        out = []
        for cmd in self.decoder.feed(data):
            ax = self.axes.get(cmd.axis)
            if ax is None:
                continue  # no such axis on this controller: nobody answers
            if isinstance(cmd, controller.UnknownCommand):
                ax.error = controller.ERR_UNKNOWN
                continue
            ans = self._do(cmd, ax)
            if ans is not None:
                out.append(controller.encode(ans))
        return out

    def _do(
        self, cmd: controller.ControllerCommand, ax: Axis
    ) -> controller.ControllerAnswer | None:
        if cmd.query:
            return self._query(cmd, ax)
        mnemonic = cmd.command
        if cmd.value is None and mnemonic in controller.SET_COMMANDS:
            ax.error = controller.ERR_UNKNOWN  # a setting without its number
            return None
        value = int(cmd.value or 0)
        if mnemonic in (Mnemonic.VELOCITY, Mnemonic.SOFT_LIMIT_LOW, Mnemonic.SOFT_LIMIT_HIGH):
            err = _set(ax, mnemonic, value)
        else:
            err = _act(ax, mnemonic, value)
        if err:
            ax.error = err
        return None

    def _query(self, cmd: controller.ControllerCommand, ax: Axis) -> controller.ControllerAnswer:
        """The answer to a query: the identity, the last error (which it clears), or a number of
        the axis."""
        n, mnemonic = cmd.axis, cmd.command
        if mnemonic == Mnemonic.IDENTITY:
            return controller.ControllerAnswer(n, mnemonic, text=f"{self.model} {self.serial}")
        if mnemonic == Mnemonic.LAST_ERROR:
            code, ax.error = ax.error, controller.ERR_NONE
            return controller.ControllerAnswer(n, mnemonic, code)
        value = {
            Mnemonic.POSITION: lambda: ax.position_pulses(),
            Mnemonic.STATE: lambda: ax.state,
            Mnemonic.VELOCITY: lambda: int(ax.velocity_pps),
            Mnemonic.SOFT_LIMIT_LOW: lambda: ax.soft[0] if ax.soft else -NO_LIMIT,
            Mnemonic.SOFT_LIMIT_HIGH: lambda: ax.soft[1] if ax.soft else NO_LIMIT,
        }[mnemonic]()
        return controller.ControllerAnswer(n, mnemonic, value)

    def readdress(self, frame: bytes) -> bytes:
        """The answer as an axis this controller does not have would give it."""
        other = next(n for n in range(9, 0, -1) if n not in self.axes)
        return str(other).encode() + frame[1:]


def _set(ax: Axis, mnemonic: Mnemonic, value: int) -> int:
    """A setting of the axis (velocity, a soft limit); the error code a bad value earns."""
    if mnemonic == Mnemonic.VELOCITY:
        if value <= 0:
            return controller.ERR_UNKNOWN
        ax.velocity_pps = float(value)
        return controller.ERR_NONE
    lo, hi = ax.soft if ax.soft else (-NO_LIMIT, NO_LIMIT)
    ax.soft = (value, hi) if mnemonic == Mnemonic.SOFT_LIMIT_LOW else (lo, value)
    return controller.ERR_NONE


def _act(ax: Axis, mnemonic: Mnemonic, value: int) -> int:
    """A motion of the axis (move, stop, home); the error code it earns (a limit, a fault)."""
    if mnemonic == Mnemonic.MOVE_TO:
        return ax.move_to(value)
    if mnemonic == Mnemonic.MOVE_BY:
        return ax.move_to(ax.position_pulses() + value)
    if mnemonic == Mnemonic.STOP:
        ax.stop()
    elif mnemonic == Mnemonic.HOME:
        return ax.home()
    return controller.ERR_NONE
