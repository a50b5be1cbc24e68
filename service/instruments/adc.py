"""Family (C): an analog tilt sensor behind a 12-bit ADC (0-5 V in 4096 counts), ASCII lines ending
CR LF.

    ADC?       -> ADC,<counts>                 one conversion, 0-4095
    ADC? <n>   -> ADC,<mean, one decimal>,<n>  mean of n conversions, 1 <= n <= 1000
    ID?        -> ID,<model>,<serial>

The family carries no checksum: a line is accepted only if all of it has the grammar
(counts within the ADC's range, the echoed n), and noise before it is cut at the last
non-printable byte. A digit changed on the line cannot be seen by any parser.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from service.instruments.framing import Parsed, ParseStats, ascii_lines, reject_line

COUNTS = 4096
MAX_CONVERSIONS = 1000
EOL = b"\r\n"


@dataclass(frozen=True)
class AdcRequest:
    """`conversions` None is a single conversion (`ADC?`); `identify` asks `ID?`."""

    conversions: int | None = None
    identify: bool = False


@dataclass(frozen=True)
class AdcCounts:
    counts: float
    conversions: int | None = None  # None: a single conversion, counts is a whole number


@dataclass(frozen=True)
class AdcIdentity:
    model: str
    serial: str


AdcAnswer = AdcCounts | AdcIdentity
AdcMessage = AdcRequest | AdcAnswer

_FIELD = r"[!-+\--~]+"  # printable, no space, no comma
_REQ = re.compile(r"ADC\?(?: ([1-9]\d{0,3}))?|(ID\?)")
_ONE = re.compile(r"ADC,(\d{1,4})")
_MEAN = re.compile(r"ADC,(\d{1,4}\.\d),([1-9]\d{0,3})")
_ID = re.compile(rf"ID,({_FIELD}),({_FIELD})")


def encode_request(msg: AdcRequest) -> bytes:
    if msg.identify:
        return b"ID?" + EOL
    if msg.conversions is None:
        return b"ADC?" + EOL
    if not 1 <= msg.conversions <= MAX_CONVERSIONS:
        raise ValueError(f"conversions {msg.conversions} must be 1..{MAX_CONVERSIONS}")
    return f"ADC? {msg.conversions}".encode() + EOL


def encode_answer(msg: AdcAnswer) -> bytes:
    if isinstance(msg, AdcIdentity):
        for field in (msg.model, msg.serial):
            if not re.fullmatch(_FIELD, field):
                raise ValueError(f"{field!r} must be printable ASCII without spaces or commas")
        return f"ID,{msg.model},{msg.serial}".encode() + EOL
    if not 0 <= msg.counts <= COUNTS - 1:
        raise ValueError(f"counts {msg.counts} outside 0..{COUNTS - 1}")
    if msg.conversions is None:
        if msg.counts != int(msg.counts):
            raise ValueError("a single conversion is a whole number of counts")
        return f"ADC,{int(msg.counts)}".encode() + EOL
    return f"ADC,{msg.counts:.1f},{msg.conversions}".encode() + EOL


def encode(msg: AdcMessage) -> bytes:
    return encode_request(msg) if isinstance(msg, AdcRequest) else encode_answer(msg)


_SECOND_HEAD = re.compile(rb".(?:ADC|ID)[,?]")


def parse_requests(buf: bytes) -> Parsed[AdcRequest]:
    st = ParseStats()
    out: list[AdcRequest] = []
    lines, rest = ascii_lines(buf, st, _SECOND_HEAD)
    for line in lines:
        m = _REQ.fullmatch(line)
        if m is None or (m[1] is not None and int(m[1]) > MAX_CONVERSIONS):
            reject_line(st, line)
            continue
        out.append(AdcRequest(identify=True) if m[2] else AdcRequest(int(m[1]) if m[1] else None))
        st.frames += 1
    return Parsed(out, rest, st)


def parse_answers(buf: bytes) -> Parsed[AdcAnswer]:
    st = ParseStats()
    out: list[AdcAnswer] = []
    lines, rest = ascii_lines(buf, st, _SECOND_HEAD)
    for line in lines:
        msg: AdcAnswer | None = None
        if m := _ONE.fullmatch(line):
            msg = AdcCounts(float(int(m[1])))
        elif m := _MEAN.fullmatch(line):
            msg = AdcCounts(float(m[1]), int(m[2]))
        elif m := _ID.fullmatch(line):
            msg = AdcIdentity(m[1], m[2])
        if isinstance(msg, AdcCounts) and (
            msg.counts > COUNTS - 1 or (msg.conversions or 1) > MAX_CONVERSIONS
        ):
            msg = None
        if msg is None:
            reject_line(st, line)
            continue
        out.append(msg)
        st.frames += 1
    return Parsed(out, rest, st)
