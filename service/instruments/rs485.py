"""Family (B): high-resolution addressable inclinometers on an RS-485 bus, ASCII with an XOR
checksum.

    request  #aaRD<CR>                                    (also ID, ZR, ZA)
    answer   #aaRD X=+1.234 Y=-0.567 T=+21.40 ST=0 *CS<CR><LF>

`aa` is the instrument's two hexadecimal digits; only the addressed instrument answers.
X and Y are milliradians with three decimals, T °C with two, ST 0 valid / 1 out of range /
2 not settled. CS is two upper-case hex digits, the XOR of every character between `#` and
` *`. Lines are read from their last `#`, so noise before a frame costs nothing but itself.

A thermo-hygrometer of the same family (a bench's ambient sensor, on its own port or the bus)
answers `#aaTH` with the air's temperature and relative humidity, and `#aaID` as above:

    request  #aaTH<CR>
    answer   #aaTH T=+20.31 RH=45.2 ST=0 *CS<CR><LF>

T in °C with two decimals, RH in percent with one, ST 0 valid / 1 out of range.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from functools import reduce

from service.instruments.framing import MAX_PENDING_BYTES, Parsed, ParseStats

COMMANDS = ("RD", "ID", "ZR", "ZA", "TH")


@dataclass(frozen=True)
class Rs485Request:
    address: int
    command: str  # RD, ID, ZR, ZA; TH (thermo-hygrometer)


@dataclass(frozen=True)
class Rs485Reading:
    address: int
    x_mrad: float
    y_mrad: float
    temp_c: float
    status: int


@dataclass(frozen=True)
class Rs485Identity:
    address: int
    model: str
    serial: str
    firmware: str


@dataclass(frozen=True)
class Rs485ZeroDone:
    address: int
    relative: bool


@dataclass(frozen=True)
class Rs485Ambient:
    """A thermo-hygrometer's answer: the air's temperature (°C) and relative humidity (%)."""

    address: int
    temp_c: float
    humidity_pct: float
    status: int


Rs485Answer = Rs485Reading | Rs485Identity | Rs485ZeroDone | Rs485Ambient
Rs485Message = Rs485Request | Rs485Answer

_NUM3 = r"[+-]\d{1,6}\.\d{3}"
_RD = re.compile(rf"RD X=({_NUM3}) Y=({_NUM3}) T=([+-]\d{{1,3}}\.\d{{2}}) ST=([0-2])")
_WORD = r"[!$-)+-~]+"  # printable, no space, '#' or '*'
_ID = re.compile(rf"ID ({_WORD}) SN=({_WORD}) FW=({_WORD})")
_ZERO = re.compile(r"(ZR|ZA) OK")
_TH = re.compile(r"TH T=([+-]\d{1,3}\.\d{2}) RH=(\d{1,3}\.\d) ST=([01])")
_REQUEST = re.compile(rb"#([0-9A-Fa-f]{2})(RD|ID|ZR|ZA|TH)")
_HEX = frozenset(b"0123456789ABCDEF")


def checksum(payload: str) -> str:
    return f"{reduce(lambda a, c: a ^ c, payload.encode('ascii'), 0):02X}"


def _addr(a: int) -> str:
    if not 0 <= a <= 0xFF:
        raise ValueError(f"RS-485 address {a} is not two hex digits")
    return f"{a:02X}"


def _word(text: str, what: str) -> str:
    if not re.fullmatch(_WORD, text):
        raise ValueError(f"{what} {text!r} must be printable ASCII without spaces, '#' or '*'")
    return text


def encode_request(msg: Rs485Request) -> bytes:
    if msg.command not in COMMANDS:
        raise ValueError(f"{msg.command!r} is not a command of the RS-485 inclinometer")
    return f"#{_addr(msg.address)}{msg.command}\r".encode("ascii")


def _reading_payload(address: str, msg: Rs485Reading) -> str:
    """An RD answer's payload; refused when the status or a value does not fit its fields."""
    if msg.status not in (0, 1, 2):
        raise ValueError(f"status {msg.status} is not 0, 1 or 2")
    payload = (
        f"{address}RD X={msg.x_mrad:+.3f} Y={msg.y_mrad:+.3f} T={msg.temp_c:+.2f} ST={msg.status}"
    )
    for value, limit in ((msg.x_mrad, 1e6), (msg.y_mrad, 1e6), (msg.temp_c, 1e3)):
        if not abs(round(value, 3)) < limit:
            raise ValueError(f"{value!r} is out of the range the answer carries")
    return payload


def _ambient_payload(address: str, msg: Rs485Ambient) -> str:
    """A TH answer's payload; refused when the status or a value does not fit its fields."""
    if msg.status not in (0, 1):
        raise ValueError(f"status {msg.status} is not 0 or 1")
    if not (abs(round(msg.temp_c, 2)) < 1e3 and 0.0 <= round(msg.humidity_pct, 1) < 1e3):
        raise ValueError(
            f"T={msg.temp_c!r}, RH={msg.humidity_pct!r} are out of the range the answer carries"
        )
    return f"{address}TH T={msg.temp_c:+.2f} RH={msg.humidity_pct:.1f} ST={msg.status}"


def encode_answer(msg: Rs485Answer) -> bytes:
    address = _addr(msg.address)
    if isinstance(msg, Rs485Reading):
        payload = _reading_payload(address, msg)
    elif isinstance(msg, Rs485Ambient):
        payload = _ambient_payload(address, msg)
    elif isinstance(msg, Rs485Identity):
        payload = (
            f"{address}ID {_word(msg.model, 'model')} SN={_word(msg.serial, 'serial')} "
            f"FW={_word(msg.firmware, 'firmware')}"
        )
    else:
        payload = f"{address}{'ZR' if msg.relative else 'ZA'} OK"
    return f"#{payload} *{checksum(payload)}\r\n".encode("ascii")


def encode(msg: Rs485Message) -> bytes:
    return encode_request(msg) if isinstance(msg, Rs485Request) else encode_answer(msg)


def _parse_answer_line(line: bytes) -> Rs485Answer | str:
    """An answer, or 'checksum' / 'malformed'."""
    if len(line) < 7 or line[-4:-2] != b" *" or not set(line[-2:]) <= _HEX:
        return "malformed"
    try:
        payload = line[1:-4].decode("ascii")
    except UnicodeDecodeError:
        return "malformed"
    if checksum(payload) != line[-2:].decode("ascii"):
        return "checksum"
    head, body = payload[:2], payload[2:]
    if not re.fullmatch(r"[0-9A-F]{2}", head):
        return "malformed"
    return _answer_of(int(head, 16), body)


def _answer_of(address: int, body: str) -> Rs485Answer | str:
    """The answer a checked line's body (after the address) has the grammar of, or 'malformed'."""
    if m := _RD.fullmatch(body):
        return Rs485Reading(address, float(m[1]), float(m[2]), float(m[3]), int(m[4]))
    if m := _ID.fullmatch(body):
        return Rs485Identity(address, m[1], m[2], m[3])
    if m := _ZERO.fullmatch(body):
        return Rs485ZeroDone(address, m[1] == "ZR")
    if m := _TH.fullmatch(body):
        return Rs485Ambient(address, float(m[1]), float(m[2]), int(m[3]))
    return "malformed"


def parse_answers(buf: bytes) -> Parsed[Rs485Answer]:
    """Answers as the daemon reads them off the bus (lines ending CR LF)."""
    out: list[Rs485Answer] = []
    st = ParseStats()
    *lines, rest = buf.split(b"\n")
    for raw in lines:
        start = raw.rfind(b"#")
        if start < 0:
            st.resyncs += 1
            st.skipped_bytes += len(raw) + 1
            continue
        if start > 0:
            st.resyncs += 1
            st.skipped_bytes += start
        line = raw[start:]
        if not line.endswith(b"\r"):
            st.resyncs += 1
            st.skipped_bytes += len(line) + 1
            continue
        got = _parse_answer_line(line[:-1])
        if got == "checksum":
            st.bad_checksum += 1
            st.skipped_bytes += len(line) + 1
        elif isinstance(got, str):  # "malformed"
            st.resyncs += 1
            st.skipped_bytes += len(line) + 1
        else:
            out.append(got)
            st.frames += 1
    return Parsed(out, _pending_answer(rest, st), st)


def _pending_answer(rest: bytes, st: ParseStats) -> bytes:
    """The unfinished tail to keep for the next read: from its last '#', or nothing when it has
    none or is longer than any answer (what is dropped is counted)."""
    start = rest.rfind(b"#")
    if start != 0 or len(rest) > MAX_PENDING_BYTES:
        if rest:
            st.resyncs += 1
            keep = rest[start:] if 0 <= start and len(rest) - start <= MAX_PENDING_BYTES else b""
            st.skipped_bytes += len(rest) - len(keep)
            rest = keep
    return rest


def parse_requests(buf: bytes) -> Parsed[Rs485Request]:
    """Requests as an instrument on the bus reads them (each ends with CR)."""
    out: list[Rs485Request] = []
    st = ParseStats()
    *lines, rest = buf.split(b"\r")
    for raw in lines:
        start = raw.rfind(b"#")
        if start != 0:
            st.resyncs += 1
        m = _REQUEST.fullmatch(raw[start:]) if start >= 0 else None
        if m is None:
            st.skipped_bytes += len(raw) + 1
            if start == 0:
                st.resyncs += 1
            continue
        st.skipped_bytes += start
        out.append(Rs485Request(int(m[1], 16), m[2].decode()))
        st.frames += 1
    start = rest.rfind(b"#")
    if start != 0 and rest:
        st.resyncs += 1
        keep = rest[start:] if start >= 0 else b""
        st.skipped_bytes += len(rest) - len(keep)
        rest = keep
    if len(rest) > 16:  # no request is longer
        st.resyncs += 1
        st.skipped_bytes += len(rest)
        rest = b""
    return Parsed(out, rest, st)


def mrad_to_deg(mrad: float) -> float:
    return math.degrees(mrad / 1000.0)


def deg_to_mrad(deg: float) -> float:
    return math.radians(deg) * 1000.0
