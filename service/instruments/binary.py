"""Family (A): biaxial inclinometers (and the triaxial module) speaking 0x68 binary frames.

    0x68 | LEN | ADDR | CMD | DATA ... | CS

LEN counts LEN..CS; CS = (LEN + ADDR + CMD + ΣDATA) & 0xFF.

Angles travel as 4 bytes of packed BCD (sign nibble, 3 integer digits, 4 decimals, degrees),
temperatures as 3 (sign, 3 integer, 2 decimals, °C), the triaxial module's sines as 4 (sign,
1 integer, 6 decimals, g). Answers carry CMD | 0x80 and the instrument's own address.

A one-byte sum cannot catch every damage, so a frame is accepted only if its length is the
one its command has, every BCD nibble is a digit and its sign nibble 0 or 1: a damaged frame
is dropped, counted, and the search restarts one byte after its start.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar

from service.instruments.framing import Parsed, ParseStats

T = TypeVar("T")

HEADER = 0x68

READ_X, READ_Y, READ_XY, SET_ZERO, READ_TEMP, READ_SINES = 0x01, 0x02, 0x04, 0x05, 0x06, 0x07
SET_BAUD, SET_OUTPUT, SET_ADDRESS = 0x0B, 0x0C, 0x0F
ANSWER = 0x80

ZERO_ABSOLUTE, ZERO_RELATIVE = 0x00, 0x01
STATUS_DONE, STATUS_REFUSED = 0x00, 0xFF
BAUD_CODES = {0x00: 2400, 0x01: 4800, 0x02: 9600, 0x03: 19200, 0x04: 38400, 0x05: 115200}
CODE_OF_BAUD = {baud: code for code, baud in BAUD_CODES.items()}
# Output mode code -> frames per second (0: answers only; None: continuous, back to back at the line
# rate).
OUTPUT_MODES: dict[int, float | None] = {
    0x00: 0.0,
    0x01: 5.0,
    0x02: 15.0,
    0x03: 25.0,
    0x04: 35.0,
    0x05: 50.0,
    0x06: 100.0,
    0x07: None,
}

# Request commands and whether they carry one argument byte.
REQUEST_ARG = {
    READ_X: False,
    READ_Y: False,
    READ_XY: False,
    READ_TEMP: False,
    READ_SINES: False,
    SET_ZERO: True,
    SET_BAUD: True,
    SET_ADDRESS: True,
    SET_OUTPUT: True,
}
# Answer commands and their DATA length.
ANSWER_DATA_LEN = {
    READ_X | ANSWER: 4,
    READ_Y | ANSWER: 4,
    READ_XY | ANSWER: 8,
    READ_TEMP | ANSWER: 3,
    READ_SINES | ANSWER: 12,
    SET_ZERO | ANSWER: 1,
    SET_BAUD | ANSWER: 1,
    SET_ADDRESS | ANSWER: 1,
    SET_OUTPUT | ANSWER: 1,
}
STATUS_ANSWERS = {SET_ZERO | ANSWER, SET_BAUD | ANSWER, SET_ADDRESS | ANSWER, SET_OUTPUT | ANSWER}
_LEN_OK = {"request": {4, 5}, "answer": {4 + n for n in ANSWER_DATA_LEN.values()}}


class BcdError(ValueError):
    """A value that packed BCD of this width cannot carry, or bytes that are not packed BCD."""


@dataclass(frozen=True)
class BinaryRequest:
    address: int
    command: int
    argument: int | None = None


@dataclass(frozen=True)
class BinaryAnswer:
    """One answer frame, its DATA decoded. Which fields are set depends on the command."""

    address: int
    command: int  # with the 0x80 bit
    x_deg: float | None = None
    y_deg: float | None = None
    temp_c: float | None = None
    sines: tuple[float, float, float] | None = None
    status: int | None = None


BinaryMessage = BinaryRequest | BinaryAnswer


# --- packed BCD -------------------------------------------------------------------------------


def encode_bcd(value: float, int_digits: int, decimals: int) -> bytes:
    """Sign nibble then int_digits + decimals digits, rounded to the last decimal."""
    scaled = round(abs(value) * 10**decimals)
    digits = int_digits + decimals
    if scaled >= 10**digits:
        raise BcdError(f"{value!r} does not fit {int_digits} integer digits")
    sign = 1 if value < 0 and scaled else 0
    text = f"{sign}{scaled:0{digits}d}"
    return bytes.fromhex(text)


def decode_bcd(data: bytes, decimals: int) -> float:
    text = data.hex()
    if not text.isdigit() or text[0] not in "01":
        raise BcdError(f"{data.hex(' ')} is not signed packed BCD")
    value: float = int(text[1:]) / 10**decimals
    return -value if text[0] == "1" else value


def encode_angle(deg: float) -> bytes:
    return encode_bcd(deg, 3, 4)


def encode_temperature(temp_c: float) -> bytes:
    return encode_bcd(temp_c, 3, 2)


def encode_sine(s: float) -> bytes:
    return encode_bcd(s, 1, 6)


# --- frames -----------------------------------------------------------------------------------


def frame(address: int, command: int, data: bytes = b"") -> bytes:
    if not (0 <= address <= 0xFF and 0 <= command <= 0xFF):
        raise ValueError("address and command are single bytes")
    length = 4 + len(data)
    cs = (length + address + command + sum(data)) & 0xFF
    return bytes([HEADER, length, address, command]) + bytes(data) + bytes([cs])


def encode_request(msg: BinaryRequest) -> bytes:
    if msg.command not in REQUEST_ARG:
        raise ValueError(f"0x{msg.command:02X} is not a request of the binary protocol")
    if REQUEST_ARG[msg.command] != (msg.argument is not None):
        raise ValueError(
            f"request 0x{msg.command:02X} {'needs' if REQUEST_ARG[msg.command] else 'takes no'} "
            "argument"
        )
    return frame(msg.address, msg.command, b"" if msg.argument is None else bytes([msg.argument]))


def encode_answer(msg: BinaryAnswer) -> bytes:
    command = msg.command
    if command in (READ_X | ANSWER, READ_Y | ANSWER):
        value = msg.x_deg if command == READ_X | ANSWER else msg.y_deg
        data = encode_angle(_given(value, command))
    elif command == READ_XY | ANSWER:
        data = encode_angle(_given(msg.x_deg, command)) + encode_angle(_given(msg.y_deg, command))
    elif command == READ_TEMP | ANSWER:
        data = encode_temperature(_given(msg.temp_c, command))
    elif command == READ_SINES | ANSWER:
        if msg.sines is None:
            raise ValueError("answer 0x87 needs three sines")
        data = b"".join(encode_sine(sine) for sine in msg.sines)
    elif command in STATUS_ANSWERS:
        data = bytes([_given(msg.status, command)])
    else:
        raise ValueError(f"0x{command:02X} is not an answer of the binary protocol")
    return frame(msg.address, command, data)


def encode(msg: BinaryMessage) -> bytes:
    return encode_request(msg) if isinstance(msg, BinaryRequest) else encode_answer(msg)


def _given(value: T | None, command: int) -> T:
    if value is None:
        raise ValueError(f"answer 0x{command:02X} lacks a value")
    return value


def _decode_answer(address: int, command: int, data: bytes) -> BinaryAnswer:
    if command in (READ_X | ANSWER, READ_Y | ANSWER):
        angle_deg = decode_bcd(data, 4)
        return (
            BinaryAnswer(address, command, x_deg=angle_deg)
            if command == READ_X | ANSWER
            else BinaryAnswer(address, command, y_deg=angle_deg)
        )
    if command == READ_XY | ANSWER:
        return BinaryAnswer(
            address, command, x_deg=decode_bcd(data[:4], 4), y_deg=decode_bcd(data[4:], 4)
        )
    if command == READ_TEMP | ANSWER:
        return BinaryAnswer(address, command, temp_c=decode_bcd(data, 2))
    if command == READ_SINES | ANSWER:
        return BinaryAnswer(
            address,
            command,
            sines=(decode_bcd(data[0:4], 6), decode_bcd(data[4:8], 6), decode_bcd(data[8:12], 6)),
        )
    status = data[0]
    if status not in (STATUS_DONE, STATUS_REFUSED):
        raise BcdError(f"status byte 0x{status:02X}")
    return BinaryAnswer(address, command, status=status)


def _decode_message(direction: str, address: int, command: int, data: bytes) -> BinaryMessage:
    """The request or answer in a frame whose length and checksum hold; BcdError when its command
    or its data length is not one the family has (a damaged frame)."""
    if direction == "request":
        if command not in REQUEST_ARG or REQUEST_ARG[command] != (len(data) == 1):
            raise BcdError("unknown request")
        return BinaryRequest(address, command, data[0] if data else None)
    if ANSWER_DATA_LEN.get(command) != len(data):
        raise BcdError("unknown answer")
    return _decode_answer(address, command, data)


def _parse(buf: bytes, direction: str) -> Parsed[BinaryMessage]:
    out: list[BinaryMessage] = []
    st = ParseStats()
    lens_ok = _LEN_OK[direction]
    i, n = 0, len(buf)
    while True:
        j = buf.find(HEADER, i)
        if j < 0:
            if i < n:
                st.resyncs += 1
                st.skipped_bytes += n - i
            return Parsed(out, b"", st)
        if j > i:
            st.resyncs += 1
            st.skipped_bytes += j - i
        if n - j < 2:
            return Parsed(out, buf[j:], st)
        length = buf[j + 1]
        if length not in lens_ok:
            st.resyncs += 1
            st.skipped_bytes += 1
            i = j + 1
            continue
        end = j + 1 + length
        if end > n:
            return Parsed(out, buf[j:], st)
        body = buf[j + 1 : end - 1]
        if sum(body) & 0xFF != buf[end - 1]:
            st.bad_checksum += 1
            st.skipped_bytes += 1
            i = j + 1
            continue
        address, command, data = body[1], body[2], body[3:]
        try:
            msg = _decode_message(direction, address, command, data)
        except BcdError:
            st.resyncs += 1
            st.skipped_bytes += 1
            i = j + 1
            continue
        out.append(msg)
        st.frames += 1
        i = end


def parse_requests(buf: bytes) -> Parsed[BinaryMessage]:
    """What an instrument reads: requests (the simulated firmware's side)."""
    return _parse(buf, "request")


def parse_answers(buf: bytes) -> Parsed[BinaryMessage]:
    """What the daemon reads: answers and unsolicited automatic-output frames."""
    return _parse(buf, "answer")


def frame_time_s(n_bytes: int, baud: int) -> float:
    """Time one frame takes on an 8N1 line (10 bits per byte)."""
    return n_bytes * 10.0 / baud
