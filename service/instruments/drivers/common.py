"""What every driver shares, whatever its family: the port, the counters, the readings kept,
polling.

Units are converted in the drivers and nowhere else: packed BCD degrees, milliradians and pulses
come in, degrees leave. A driver never knows whether a simulator or an instrument answers.
"""

from __future__ import annotations

import asyncio
import bisect
import collections
import contextlib
import datetime as dt
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from service.clock import Clock
from service.instruments.base import DeviceCounters, DeviceIdentity, DeviceStatus, Reading
from service.instruments.transport import DeviceError, DeviceTimeout, SerialPort

T = TypeVar("T")


def present(value: T | None, what: str) -> T:
    """A field the answer must carry; an answer without it is the instrument's error, said as
    one."""
    if value is None:
        raise DeviceError(f"{what}: the answer lacks its value")
    return value


def _bench_s(reading: Reading) -> float:
    return reading.bench_s


# per driver: 10 min at 25 Hz (the longest averaged tilt), over 30 s of a sped-up continuous output
RECENT_READINGS = 16384


class SerialDriver:
    """What every driver shares: its port, its counters, its identity and latest reading."""

    protocol = ""

    def __init__(self, role: str, port: SerialPort, clock: Clock, timeout_s: float) -> None:
        self.role = role
        self.port = port
        self.clock = clock
        self.timeout_s = timeout_s
        self.identity: DeviceIdentity | None = None
        self.timeouts = 0
        # Every reading, not only the latest: waiting for settled readings must not depend on how
        # often the waiting side looks (a sped-up bench sends hundreds a second).
        self.recent: collections.deque[Reading] = collections.deque(maxlen=RECENT_READINGS)
        self._last: Reading | None = None
        self._poll_task: asyncio.Task[None] | None = None
        # the read a polling driver repeats
        self._poll_read: Callable[[], Awaitable[Reading]] | None = None
        self._poll_reading = False  # a read of the polling loop is in flight

    @property
    def _latest(self) -> Reading | None:
        return self._last

    @_latest.setter
    def _latest(self, reading: Reading | None) -> None:
        self._last = reading
        if reading is not None:
            self.recent.append(reading)

    def readings_after(self, bench_s: float) -> list[Reading]:
        """The readings kept that are stamped after `bench_s` (bench seconds), oldest first."""
        # one C call under the GIL: safe against the reader thread appending
        kept = list(self.recent)
        # stamped in arrival order, so sorted: the stream asks every few milliseconds for the newest
        # few
        return kept[bisect.bisect_right(kept, bench_s, key=_bench_s) :]

    @property
    def status(self) -> DeviceStatus:
        st = self.port.decoder.stats
        return DeviceStatus(
            role=self.role,
            port=self.port.where,
            protocol=self.protocol,
            state=self.port.state,
            last_frame_utc=self.port.last_frame_utc,
            counters=DeviceCounters(
                frames=st.frames,
                bad_checksum=st.bad_checksum,
                resyncs=st.resyncs,
                timeouts=self.timeouts,
                reconnects=self.port.reconnects,
                wrong_address=self.port.wrong_address,
            ),
            identity=self.identity,
            error=self.port.error,
        )

    def latest(self) -> Reading | None:
        return self._latest

    async def sync(self) -> float:
        """A mark in the reading stream (bench seconds): every reading stamped after it was produced
        after this call. Readings are stamped when they are parsed, so a reader that lags (a loaded
        machine, a sped-up bench) hands out, after a move, readings the instrument made during it;
        a caller that needs readings of the present pose counts only those after the mark.

        A polling driver reads once more: requests on a port go one at a time, so every reading
        stamped after this one was asked for after it. A driver that reads only when asked: the
        present time (nothing older can arrive later).
        """
        if self._poll_read is not None and self._poll_task is not None:
            return float((await self._poll_read()).bench_s)
        return self.clock.monotonic()

    def _stamp(self, **fields: Any) -> Reading:
        return Reading(
            role=self.role,
            bench_s=self.clock.monotonic(),
            time_utc=dt.datetime.now(dt.UTC),
            **fields,
        )

    async def _ask(
        self,
        data: bytes,
        match: Callable[[Any], bool],
        what: str,
        *,
        timeout_s: float | None = None,
    ) -> Any:
        try:
            return await self.port.request(
                data, match, timeout_s or self.timeout_s, f"{self.role}: {what}"
            )
        except DeviceTimeout:
            self.timeouts += 1
            raise

    async def start(self) -> None:
        """Start the port's reader and give it a moment to open; a port that does not open keeps
        trying."""
        self.port.start()
        await asyncio.to_thread(self.port.wait_connected, self.timeout_s * 4)

    async def stop_polling(self, *, finish_read: bool = True) -> None:
        """No more reads of its own (a caller that wants the line to itself, as a probe or a test).

        A read in flight is let finish (by its answer or its timeout) unless `finish_read` is false:
        cancelled, its answer would still come and could be taken for the caller's next request."""
        task, self._poll_task = self._poll_task, None
        if task is None:
            return
        if finish_read and self._poll_reading:
            # the loop ends after this read
            await asyncio.wait({task}, timeout=self.timeout_s + 1.0)
        while not task.done():
            task.cancel()
            await asyncio.wait({task}, timeout=0.1)
        with contextlib.suppress(asyncio.CancelledError, Exception):
            task.result()

    async def close(self) -> None:
        await self.stop_polling(finish_read=False)
        self.port.stop()

    def _start_polling(self, rate_hz: float, read: Callable[[], Awaitable[Reading]]) -> None:
        self._poll_read = read

        async def poll() -> None:
            while self._poll_task is not None:
                self._poll_reading = True
                try:
                    with contextlib.suppress(DeviceError):
                        await read()
                finally:
                    self._poll_reading = False
                if self._poll_task is None:
                    return
                # bench time: a sped-up bench is polled faster too
                await self.clock.sleep(1.0 / rate_hz)

        self._poll_task = asyncio.get_running_loop().create_task(poll())
