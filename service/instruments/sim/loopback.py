"""An in-memory serial line between a driver's port and a simulated instrument: no pseudo-terminal.

A bench configuration names such a line `simloop://NAME`. pyserial finds its handler
(`protocol_simloop` in this package) through `serial.protocol_handler_packages`, so the port
transport, its reader thread and the drivers are the very ones that open a pty or a USB adapter;
the firmware reads requests and writes answers with the same codecs as on a pty. The line lives
in this process only: it serves tests (and in-process daemons) where the pty itself is not under
test. Pulling the cable (`Faults.disconnect`) works as on a pty: the open end fails its next read,
and the name cannot be opened until the line is plugged in again.
"""

from __future__ import annotations

import itertools
import threading
from pathlib import Path

import serial

from service.instruments.sim.pty import Firmware, SimPort

SCHEME = "simloop"
HANDLER_PACKAGE = "service.instruments.sim"  # holds protocol_simloop, found by serial_for_url
# A pty keeps about this much for a reader that is not reading; past it, bytes are lost.
HOST_BUFFER_BYTES = 65536

_lines: dict[str, MemoryLine] = {}
_lines_lock = threading.Lock()
_numbers = itertools.count(1)


class LineGone(serial.SerialException):  # type: ignore[misc]  # pyserial ships no type information
    """The line was unplugged under an open end, or its name is not (or no longer) a line."""


class MemoryLine:
    """Both directions of one line, and whether its cable is in."""

    def __init__(self, label: str) -> None:
        self.url = f"{SCHEME}://{label}-{next(_numbers)}"
        self._cond = threading.Condition()
        self._to_instrument = bytearray()
        self._to_host = bytearray()
        self._plugged = True
        self._generation = 0  # bumped at every unplug: an end opened before it is gone
        self._host_open = False
        self._closed = False
        with _lines_lock:
            _lines[self.url] = self

    # --- the driver's end (through pyserial) ----------------------------------------------------

    def open_host(self) -> int:
        with self._cond:
            if not self._plugged or self._closed:
                raise LineGone(f"could not open port {self.url}: no such device")
            if self._host_open:
                raise LineGone(f"could not open port {self.url}: it is open already")
            self._host_open = True
            return self._generation

    def close_host(self, generation: int) -> None:
        with self._cond:
            if generation == self._generation:
                self._host_open = False
            self._cond.notify_all()

    def _check(self, generation: int) -> None:
        if generation != self._generation or self._closed:
            raise LineGone(
                f"device reports readiness to read but returned no data ({self.url} was unplugged)"
            )

    def discard_for_host(self, generation: int) -> None:
        """Drop what waits for the driver (pyserial flushes a port's input when it opens it)."""
        with self._cond:
            self._check(generation)
            self._to_host.clear()

    def pending_for_host(self) -> int:
        """Bytes on their way to the driver that it has not read yet."""
        with self._cond:
            return len(self._to_host)

    def waiting(self, generation: int) -> int:
        with self._cond:
            self._check(generation)
            return len(self._to_host)

    def read_host(self, generation: int, size: int, timeout_s: float | None) -> bytes:
        """Up to `size` bytes: as soon as that many are there, or what came within the timeout."""
        with self._cond:
            self._cond.wait_for(
                lambda: (
                    len(self._to_host) >= size or generation != self._generation or self._closed
                ),
                timeout_s,
            )
            self._check(generation)
            data = bytes(self._to_host[:size])
            del self._to_host[:size]
            return data

    def write_host(self, generation: int, data: bytes) -> None:
        with self._cond:
            self._check(generation)
            self._to_instrument += data
            self._cond.notify_all()

    # --- the instrument's end -------------------------------------------------------------------

    def read_instrument(self, timeout_s: float) -> bytes:
        """What the driver wrote, waiting at most timeout_s for something."""
        with self._cond:
            self._cond.wait_for(lambda: bool(self._to_instrument) or self._closed, timeout_s)
            data = bytes(self._to_instrument)
            self._to_instrument.clear()
            return data

    def write_instrument(self, data: bytes) -> int:
        """Bytes towards the driver; returns how many the line kept (a full buffer loses the
        rest)."""
        with self._cond:
            if not self._plugged:
                return len(data)  # into a pulled cable: gone, as on a closed pty
            n = max(0, min(len(data), HOST_BUFFER_BYTES - len(self._to_host)))
            self._to_host += data[:n]
            self._cond.notify_all()
            return n

    def unplug(self) -> None:
        with self._cond:
            self._plugged = False
            self._generation += 1
            self._host_open = False
            self._to_host.clear()
            self._to_instrument.clear()
            self._cond.notify_all()

    def plug(self) -> None:
        with self._cond:
            self._plugged = True
            self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        with _lines_lock:
            _lines.pop(self.url, None)


def line_named(url: str) -> MemoryLine:
    with _lines_lock:
        line = _lines.get(url)
    if line is None:
        raise LineGone(
            f"could not open port {url}: no simulated instrument on that line in this process"
        )
    return line


def register_handler() -> None:
    """Let `serial.serial_for_url` open `simloop://` names (idempotent)."""
    packages: list[str] = serial.protocol_handler_packages
    if HANDLER_PACKAGE not in packages:
        packages.append(HANDLER_PACKAGE)


class LoopbackSimPort(SimPort):
    """A simulated instrument's end of a memory line: a SimPort (faults and all) without the pty."""

    def __init__(self, link: Path, firmware: Firmware) -> None:
        register_handler()
        self.line = MemoryLine(Path(link).name)
        super().__init__(link, firmware)

    @property
    def path(self) -> str:
        return self.line.url

    def _open(self) -> None:
        self.line.plug()

    def _close_pty(self) -> None:
        self.line.unplug()

    def _receive(self, timeout_s: float) -> bytes | None:
        return self.line.read_instrument(timeout_s)

    def write(self, data: bytes) -> None:
        n = self.line.write_instrument(data)
        self.sent_bytes += n
        self.overflow_bytes += len(data) - n

    def close(self) -> None:
        super().close()
        self.line.close()
