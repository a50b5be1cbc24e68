"""What every byte codec shares: parse counters and the incremental decoder around a pure parse.

Each family's codec is a pure function `parse(buffer) -> Parsed(messages, remainder, stats)`:
it takes whatever bytes have arrived and returns the complete, checked messages, the bytes
that may still become a message, and what it had to throw away. `Decoder` keeps the
remainder between reads and adds the counts up; it does no I/O, so a port reader, a
simulated firmware and a fuzz test drive it the same way.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Generic, TypeVar

M = TypeVar("M")

# A line or frame that grows past this without an end is noise; it is dropped and the search
# restarts.
MAX_PENDING_BYTES = 512


@dataclass
class ParseStats:
    """Counts of one parse (or, in a Decoder, of all parses so far)."""

    frames: int = 0  # messages returned
    bad_checksum: int = 0  # complete frames whose checksum did not match
    # times bytes were skipped to find the next frame start (garbage, malformed frames)
    resyncs: int = 0
    skipped_bytes: int = 0

    def add(self, other: ParseStats) -> None:
        self.frames += other.frames
        self.bad_checksum += other.bad_checksum
        self.resyncs += other.resyncs
        self.skipped_bytes += other.skipped_bytes


@dataclass
class Parsed(Generic[M]):
    messages: list[M]
    remainder: bytes
    stats: ParseStats = field(default_factory=ParseStats)


class Decoder(Generic[M]):
    """Feed bytes as they arrive; get complete messages back. Counts accumulate in `stats`."""

    def __init__(self, parse: Callable[[bytes], Parsed[M]]) -> None:
        self._parse = parse
        self._pending = b""
        self.stats = ParseStats()

    def feed(self, data: bytes) -> list[M]:
        out = self._parse(self._pending + bytes(data))
        self._pending = out.remainder
        self.stats.add(out.stats)
        return out.messages

    def reset(self) -> None:
        """Forget a partial frame (after a reconnect the bytes before it belong to nothing)."""
        self._pending = b""

    @property
    def pending(self) -> bytes:
        return self._pending


def ascii_lines(
    buf: bytes, st: ParseStats, second_head: re.Pattern[bytes], terminator: bytes = b"\r\n"
) -> tuple[list[str], bytes]:
    """Complete lines of an ASCII family without checksum, and the unterminated rest.

    Noise before a line is cut at its last non-printable byte; a line that holds a second
    message head (`second_head` matches after its first byte: two lines run together
    because a terminator was lost) is dropped whole. Dropped bytes are counted in `st`.
    """
    lines, rest, dropped = split_lines(buf, terminator)
    st.resyncs += dropped
    out = []
    for line in lines:
        tail, cut = printable_tail(line)
        if cut:
            st.resyncs += 1
            st.skipped_bytes += len(line) - len(tail)
        if second_head.search(tail):
            reject_line(st, tail)
        elif tail:
            out.append(tail.decode("ascii"))
    return out, rest


def reject_line(st: ParseStats, line: bytes | str) -> None:
    st.resyncs += 1
    st.skipped_bytes += len(line) + 2


def split_lines(
    buf: bytes, terminator: bytes, max_line: int = MAX_PENDING_BYTES
) -> tuple[list[bytes], bytes, int]:
    """Complete lines (without terminator), the unterminated rest, and how many over-long pieces
    were dropped."""
    parts = buf.split(terminator)
    rest = parts.pop()
    dropped = 0
    if len(rest) > max_line:
        rest = b""
        dropped = 1
    return parts, rest, dropped


def printable_tail(line: bytes) -> tuple[bytes, bool]:
    """The part of a line after its last byte that is not printable ASCII; True if something was
    cut.

    Line noise on an ASCII port is mostly bytes outside the printable range; cutting at
    the last one lets the line that follows the noise be read.
    """
    for i in range(len(line) - 1, -1, -1):
        if not 0x20 <= line[i] < 0x7F:
            return line[i + 1 :], True
    return line, False
