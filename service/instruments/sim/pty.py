"""A simulated instrument's end of a pseudo-terminal, with a fault back door.

The daemon opens a stable path (a symlink in the bench's folder) that points at the slave
side of a pty; the firmware reads requests from the master side and writes answers there.
A disconnect closes the pty and removes the link, and a new pty appears behind the same
path later, as a replugged USB adapter comes back under its udev name.

Faults are queued through `Faults` and applied to what the firmware sends next: garbage
bytes, dropped bytes, a corrupted checksum, a slow answer, an answer from the wrong
address, silence, a disconnect. Times of faults are real seconds: they are about the line.
"""

from __future__ import annotations

import contextlib
import heapq
import os
import random
import select
import threading
import time
import tty
from pathlib import Path
from typing import Protocol

# Automatic output leaves in bursts at most this often (real seconds), as a USB serial adapter's
# latency timer hands the host what came within it (16 ms by default on the common ones): a sped-up
# sensor's hundreds of frames a second wake the port's reader tens of times, not hundreds. Answers
# are not held back.
OUTPUT_LATENCY_S = 0.01
# the longest a port's thread sleeps with nothing due (to notice a stop or a reopen)
IDLE_WAIT_S = 0.05


class Firmware(Protocol):
    family: str

    def handle(self, data: bytes) -> list[bytes]:
        """Bytes from the line -> answers to send."""
        ...

    def due(self, now_real: float) -> list[bytes]:
        """Unsolicited frames due by now (automatic output)."""
        ...

    def next_due(self) -> float | None:
        """Real time of the next unsolicited frame, or None."""
        ...

    def corrupt_checksum(self, frame: bytes) -> bytes: ...

    def readdress(self, frame: bytes) -> bytes: ...


class Faults:
    """The back door of one simulated port. Each call queues a fault for what is sent next."""

    CHECKSUMMED = ("binary", "rs485")
    ADDRESSED = ("binary", "rs485", "controller")

    def __init__(self, port: SimPort) -> None:
        self._port = port
        self._lock = threading.Lock()
        self.drop_next = 0  # bytes to drop from the next frame
        self.corrupt_next = 0  # frames whose checksum is spoiled
        self.slow_next: list[float] = []  # delays of the next answers
        self.wrong_address_next = 0
        self.silent = False
        self.injected: dict[str, int] = {}

    def _count(self, what: str, n: int = 1) -> None:
        self.injected[what] = self.injected.get(what, 0) + n

    def garbage(self, n: int = 32, seed: int | None = None) -> bytes:
        """Write n random bytes on the line now (line noise); returns them."""
        data = random.Random(seed).randbytes(n)
        self._port.write(data)
        self._count("garbage")
        return data

    def drop_bytes(self, n: int = 1) -> None:
        """The next frame loses n bytes (in the ASCII families without a checksum: its last n,
        terminator first)."""
        with self._lock:
            self.drop_next += n
        self._count("drop")

    def corrupt_checksum(self, frames: int = 1) -> None:
        if self._port.firmware.family not in self.CHECKSUMMED:
            raise ValueError(f"family {self._port.firmware.family} carries no checksum to corrupt")
        with self._lock:
            self.corrupt_next += frames
        self._count("checksum", frames)

    def slow(self, delay_s: float, answers: int = 1) -> None:
        """The next answers leave delay_s (real seconds) late."""
        with self._lock:
            self.slow_next += [delay_s] * answers
        self._count("slow", answers)

    def wrong_address(self, answers: int = 1) -> None:
        if self._port.firmware.family not in self.ADDRESSED:
            raise ValueError(f"family {self._port.firmware.family} has no address")
        with self._lock:
            self.wrong_address_next += answers
        self._count("wrong_address", answers)

    def silence(self, on: bool = True) -> None:
        """Send nothing at all (a powered-off instrument on a live adapter)."""
        self.silent = on

    def disconnect(self, for_s: float = 0.5) -> None:
        """Close the pty now (the cable is pulled); a new one appears at the same path after
        for_s."""
        self._port.disconnect(for_s)
        self._count("disconnect")

    def take(self, frame: bytes, answer: bool) -> tuple[bytes | None, float]:
        """Apply queued faults to a frame about to be sent: the bytes (None: nothing) and the
        delay."""
        fw = self._port.firmware
        with self._lock:
            if self.silent:
                return None, 0.0
            if self.wrong_address_next and answer:
                self.wrong_address_next -= 1
                frame = fw.readdress(frame)
            if self.corrupt_next:
                self.corrupt_next -= 1
                frame = fw.corrupt_checksum(frame)
            if self.drop_next:
                n = min(self.drop_next, len(frame))
                self.drop_next -= n
                if fw.family in self.CHECKSUMMED:
                    i = random.randrange(0, len(frame) - n + 1)
                    frame = frame[:i] + frame[i + n :]
                else:
                    frame = frame[: len(frame) - n]
            delay = self.slow_next.pop(0) if (self.slow_next and answer) else 0.0
        return frame, delay


class SimPort:
    """The master side of a pty behind a stable path, served by one thread."""

    def __init__(self, link: Path, firmware: Firmware) -> None:
        self.link = Path(link)
        self.firmware = firmware
        self.faults = Faults(self)
        self.sent_frames = 0
        self.sent_bytes = 0
        self.overflow_bytes = 0  # written while nobody read and the pty buffer was full
        self._master: int | None = None
        self._slave: int | None = None
        self._wlock = threading.Lock()
        self._reopen_at: float | None = None
        self._later: list[tuple[float, int, bytes]] = []
        self._seq = 0
        self._stop = threading.Event()
        self._open()
        self._thread = threading.Thread(target=self._run, name=f"sim {self.link.name}", daemon=True)
        self._thread.start()

    @property
    def path(self) -> str:
        return str(self.link)

    def _open(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no CR/LF translation: the bytes are the protocol's
        os.set_blocking(master, False)
        tmp = self.link.with_name(self.link.name + ".new")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        tmp.symlink_to(os.ttyname(slave))
        os.replace(tmp, self.link)
        with self._wlock:
            self._master, self._slave = master, slave

    def _receive(self, timeout_s: float) -> bytes | None:
        """What the driver wrote, waiting at most timeout_s; None while the line is down."""
        master = self._master
        if master is None:
            return None
        try:
            ready, _, _ = select.select([master], [], [], timeout_s)
            return os.read(master, 4096) if ready else b""
        except (OSError, ValueError):  # closed by a disconnect meanwhile
            return None

    def _close_pty(self) -> None:
        with self._wlock:
            master, slave, self._master, self._slave = self._master, self._slave, None, None
        with contextlib.suppress(FileNotFoundError):
            self.link.unlink()
        for fd in (slave, master):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)

    def disconnect(self, for_s: float) -> None:
        self._close_pty()
        self._reopen_at = time.monotonic() + for_s

    def write(self, data: bytes) -> None:
        with self._wlock:
            if self._master is None:
                return
            try:
                n = os.write(self._master, data)
            except BlockingIOError:
                n = 0
            except OSError:
                return
        self.sent_bytes += n
        self.overflow_bytes += len(data) - n

    def _emit(self, frame: bytes, answer: bool) -> None:
        out, delay = self.faults.take(frame, answer)
        if out is None:
            return
        if delay > 0:
            self._seq += 1
            heapq.heappush(self._later, (time.monotonic() + delay, self._seq, out))
            return
        self.write(out)
        self.sent_frames += 1

    def _send_delayed(self, now: float) -> None:
        """Send the frames a fault held back whose time has come."""
        while self._later and self._later[0][0] <= now:
            self.write(heapq.heappop(self._later)[2])
            self.sent_frames += 1

    def _wait_s(self, now: float, flushed: float) -> float:
        """How long to wait for the driver's bytes: until the next automatic frame is due (no
        sooner than the output latency after the last), the next held-back frame, or IDLE_WAIT_S."""
        waits = [IDLE_WAIT_S]
        nd = self.firmware.next_due()
        if nd is not None:
            waits.append(max(nd, flushed + OUTPUT_LATENCY_S) - now)
        if self._later:
            waits.append(self._later[0][0] - now)
        return max(0.0, min(waits))

    def _run(self) -> None:
        flushed = 0.0  # real time automatic output last left
        while not self._stop.is_set():
            now = time.monotonic()
            if self._reopen_at is not None:
                if now < self._reopen_at:
                    self._stop.wait(min(0.02, self._reopen_at - now))
                    continue
                self._reopen_at = None
                self._open()
            self._send_delayed(now)
            data = self._receive(self._wait_s(now, flushed))
            if data is None:
                continue
            now = time.monotonic()
            if data or now - flushed >= OUTPUT_LATENCY_S:
                # what is due goes out before any answer: frames made before a request never follow
                # its answer
                flushed = now
                for frame in self.firmware.due(now):
                    self._emit(frame, False)
            if data:
                for answer in self.firmware.handle(data):
                    self._emit(answer, True)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._close_pty()
