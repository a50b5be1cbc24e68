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
from enum import StrEnum

from service.instruments.framing import Parsed, ParseStats, ascii_lines, reject_line

EOL = b"\r\n"


class Mnemonic(StrEnum):
    """The controller's two-letter commands, named for what they do."""

    MOVE_TO = "PA"
    MOVE_BY = "PR"
    VELOCITY = "VA"
    SOFT_LIMIT_LOW = "SL"
    SOFT_LIMIT_HIGH = "SR"
    POSITION = "TP"
    STATE = "TS"
    LAST_ERROR = "TE"
    IDENTITY = "ID"
    STOP = "ST"
    HOME = "OR"


@dataclass(frozen=True)
class Form:
    """How a mnemonic may be sent: with an integer argument (`sets`), as a query (`asks`: its
    answer a number, or for ID text), bare (`acts`)."""

    sets: bool = False
    asks: bool = False
    acts: bool = False


# The one table of the protocol: the codec's grammar, the driver and the simulator read it.
FORMS: dict[Mnemonic, Form] = {
    Mnemonic.MOVE_TO: Form(sets=True),
    Mnemonic.MOVE_BY: Form(sets=True),
    Mnemonic.VELOCITY: Form(sets=True, asks=True),
    Mnemonic.SOFT_LIMIT_LOW: Form(sets=True, asks=True),
    Mnemonic.SOFT_LIMIT_HIGH: Form(sets=True, asks=True),
    Mnemonic.POSITION: Form(asks=True),
    Mnemonic.STATE: Form(asks=True),
    Mnemonic.LAST_ERROR: Form(asks=True),
    Mnemonic.IDENTITY: Form(asks=True),
    Mnemonic.STOP: Form(acts=True),
    Mnemonic.HOME: Form(acts=True),
}
SET_COMMANDS = tuple(m for m, form in FORMS.items() if form.sets)
QUERIES = tuple(m for m, form in FORMS.items() if form.asks)
ACTIONS = tuple(m for m, form in FORMS.items() if form.acts)
NUMBER_QUERIES = tuple(m for m in QUERIES if m is not Mnemonic.IDENTITY)

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
    command: Mnemonic
    value: int | None = None
    query: bool = False


@dataclass(frozen=True)
class ControllerAnswer:
    """The answer to a query: `value` for numbers, `text` for ID (`<model> <serial>`)."""

    axis: int
    command: Mnemonic
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


def _either(mnemonics: tuple[Mnemonic, ...]) -> str:
    return "|".join(m.value for m in mnemonics)


_CMD = re.compile(
    rf"([1-9])(?:({_either(SET_COMMANDS)})({_INT})|({_either(QUERIES)})\?|({_either(ACTIONS)}))"
)
_ANS = re.compile(rf"([1-9])(?:({_either(NUMBER_QUERIES)})({_INT})|ID([!-~]+ [!-~]+))")


def _axis(n: int) -> str:
    if not 1 <= n <= 9:
        raise ValueError(f"axis {n} is not 1..9")
    return str(n)


def encode_command(msg: ControllerCommand) -> bytes:
    axis = _axis(msg.axis)
    if msg.query:
        if msg.command not in QUERIES:
            raise ValueError(f"{msg.command}? is not a query of the controller")
        return f"{axis}{msg.command}?".encode() + EOL
    if msg.command in SET_COMMANDS:
        if msg.value is None:
            raise ValueError(f"{msg.command} needs a value")
        return f"{axis}{msg.command}{int(msg.value)}".encode() + EOL
    if msg.command in ACTIONS:
        return f"{axis}{msg.command}".encode() + EOL
    raise ValueError(f"{msg.command} is not a command of the controller")


def encode_answer(msg: ControllerAnswer) -> bytes:
    axis = _axis(msg.axis)
    if msg.command == Mnemonic.IDENTITY:
        if msg.text is None or not re.fullmatch(r"[!-~]+ [!-~]+", msg.text):
            raise ValueError("an ID answer is '<model> <serial>', printable, one space")
        return f"{axis}ID{msg.text}".encode() + EOL
    if msg.command not in QUERIES or msg.value is None:
        raise ValueError(f"{msg.command} is not answered with a number")
    return f"{axis}{msg.command}{int(msg.value)}".encode() + EOL


def encode(msg: ControllerMessage) -> bytes:
    return encode_command(msg) if isinstance(msg, ControllerCommand) else encode_answer(msg)


_SECOND_HEAD = re.compile(rf".[1-9](?:{_either(tuple(FORMS))})".encode())


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
            out.append(ControllerCommand(axis, Mnemonic(m[2]), int(m[3])))
        elif m[4]:
            out.append(ControllerCommand(axis, Mnemonic(m[4]), query=True))
        else:
            out.append(ControllerCommand(axis, Mnemonic(m[5])))
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
            out.append(ControllerAnswer(int(m[1]), Mnemonic(m[2]), value=int(m[3])))
        else:
            out.append(ControllerAnswer(int(m[1]), Mnemonic.IDENTITY, text=m[4]))
        st.frames += 1
    return Parsed(out, rest, st)
