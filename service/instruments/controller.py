"""Family (D): stage and rotary-table controller, ASCII `<axis><CMD>[argument]` lines ending CR LF.

Queries end in `?` and are answered with the same axis and command and the value
(`1TP?` -> `1TP-1200`); other commands are not answered. Positions are whole pulses.

    nPA<p> nPR<p>    move to / by p          nTP?  position          nTS?  state (0..4)
    nST              stop                    nOR   home              nVA<v> / nVA?  velocity
    nSL<p> nSR<p>    soft limits (+ ? form)  nTE?  last error, then cleared
    nID?             model and serial

Like family (C), no checksum: a line is taken only if all of it has the grammar.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from service.instruments.framing import Parsed, ParseStats, ascii_lines, reject_line

EOL = b"\r\n"
# Commands with an integer argument, queries (answered with an integer, or ID with text), bare
# actions.
SET_COMMANDS = ("PA", "PR", "VA", "SL", "SR")
QUERIES = ("TP", "TS", "VA", "SL", "SR", "TE", "ID")
ACTIONS = ("ST", "OR")

STATE_READY, STATE_MOVING, STATE_HOMING, STATE_HARD_LIMIT, STATE_ERROR = 0, 1, 2, 3, 4
STATE_NAMES = {0: "ready", 1: "moving", 2: "homing", 3: "hard_limit", 4: "error"}
ERR_NONE, ERR_UNKNOWN, ERR_SOFT_LIMIT, ERR_NOT_HOMED, ERR_HARD_LIMIT, ERR_BUSY = 0, 1, 2, 3, 4, 5
ERROR_NAMES = {
    0: "none",
    1: "unknown command",
    2: "beyond a soft limit",
    3: "not homed",
    4: "hard limit",
    5: "busy",
}


@dataclass(frozen=True)
class ControllerCommand:
    """A line to the controller: `value` is the argument of a set command; `query` marks `?`
    forms."""

    axis: int
    command: str
    value: int | None = None
    query: bool = False


@dataclass(frozen=True)
class ControllerAnswer:
    """The answer to a query: `value` for numbers, `text` for ID (`<model> <serial>`)."""

    axis: int
    command: str
    value: int | None = None
    text: str | None = None


@dataclass(frozen=True)
class UnknownCommand:
    """A whole printable line addressed to an axis that is no command: the controller sets error
    1."""

    axis: int
    text: str


ControllerMessage = ControllerCommand | ControllerAnswer

_INT = r"[+-]?\d{1,10}"
_CMD = re.compile(rf"([1-9])(?:(PA|PR|VA|SL|SR)({_INT})|(TP|TS|VA|SL|SR|TE|ID)\?|(ST|OR))")
_ANS = re.compile(rf"([1-9])(?:(TP|TS|VA|SL|SR|TE)({_INT})|ID([!-~]+ [!-~]+))")


def _axis(n: int) -> str:
    if not 1 <= n <= 9:
        raise ValueError(f"axis {n} is not 1..9")
    return str(n)


def encode_command(msg: ControllerCommand) -> bytes:
    a = _axis(msg.axis)
    if msg.query:
        if msg.command not in QUERIES:
            raise ValueError(f"{msg.command}? is not a query of the controller")
        return f"{a}{msg.command}?".encode() + EOL
    if msg.command in SET_COMMANDS:
        if msg.value is None:
            raise ValueError(f"{msg.command} needs a value")
        return f"{a}{msg.command}{int(msg.value)}".encode() + EOL
    if msg.command in ACTIONS:
        return f"{a}{msg.command}".encode() + EOL
    raise ValueError(f"{msg.command} is not a command of the controller")


def encode_answer(msg: ControllerAnswer) -> bytes:
    a = _axis(msg.axis)
    if msg.command == "ID":
        if msg.text is None or not re.fullmatch(r"[!-~]+ [!-~]+", msg.text):
            raise ValueError("an ID answer is '<model> <serial>', printable, one space")
        return f"{a}ID{msg.text}".encode() + EOL
    if msg.command not in QUERIES or msg.value is None:
        raise ValueError(f"{msg.command} is not answered with a number")
    return f"{a}{msg.command}{int(msg.value)}".encode() + EOL


def encode(msg: ControllerMessage) -> bytes:
    return encode_command(msg) if isinstance(msg, ControllerCommand) else encode_answer(msg)


_SECOND_HEAD = re.compile(rb".[1-9](?:PA|PR|VA|SL|SR|TP|TS|TE|ID|ST|OR)")


def parse_commands(buf: bytes) -> Parsed[ControllerCommand | UnknownCommand]:
    """What the controller reads."""
    st = ParseStats()
    out: list[ControllerCommand | UnknownCommand] = []
    lines, rest = ascii_lines(buf, st, _SECOND_HEAD)
    for line in lines:
        m = _CMD.fullmatch(line)
        if m is None:
            if re.match(r"[1-9][A-Z]", line):
                out.append(UnknownCommand(int(line[0]), line))
                continue
            reject_line(st, line)
            continue
        axis = int(m[1])
        if m[2]:
            out.append(ControllerCommand(axis, m[2], int(m[3])))
        elif m[4]:
            out.append(ControllerCommand(axis, m[4], query=True))
        else:
            out.append(ControllerCommand(axis, m[5]))
        st.frames += 1
    return Parsed(out, rest, st)


def parse_answers(buf: bytes) -> Parsed[ControllerAnswer]:
    """What the daemon reads."""
    st = ParseStats()
    out: list[ControllerAnswer] = []
    lines, rest = ascii_lines(buf, st, _SECOND_HEAD)
    for line in lines:
        m = _ANS.fullmatch(line)
        if m is None:
            reject_line(st, line)
            continue
        if m[2]:
            out.append(ControllerAnswer(int(m[1]), m[2], value=int(m[3])))
        else:
            out.append(ControllerAnswer(int(m[1]), "ID", text=m[4]))
        st.frames += 1
    return Parsed(out, rest, st)
