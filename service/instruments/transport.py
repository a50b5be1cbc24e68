"""One serial port of the bench: its single owner, its reader, its one request in flight.

Ports are opened with pyserial's `serial_for_url`, so a device path, `socket://host:port`
and `rfc2217://host:port` all work, and a USB adapter can be named by its serial number.

Why a reader thread per port rather than pyserial-asyncio(-fast): the asyncio transports
read a file descriptor through the event loop's selector, which the `socket://` and
`rfc2217://` handlers of pyserial do not offer in the same way (rfc2217 runs its own
thread), and a family (A) instrument in continuous output delivers ~900 frames a second
that would otherwise wake the event loop for every few bytes. A thread doing blocking
reads with a short timeout works for every URL handler alike, parses off the loop, and
hands over only complete messages (`call_soon_threadsafe`). The event loop never blocks
on a port: writes go through the port's own writer thread (never the shared worker pool, where
they would queue behind database work) and answers arrive as futures.

The reader also owns the connection: a port that fails (cable pulled, adapter gone, pty
closed) is closed, every waiting request fails at once, and the port is reopened with
back-off; the state goes connected -> reconnecting -> connected (or failed once it has
been unreachable for `fail_after_s`).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import datetime as dt
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import serial
import serial.tools.list_ports

from service.instruments.base import DeviceState
from service.instruments.framing import Decoder, Parsed

BACKOFF_FIRST_S = 0.05
BACKOFF_MAX_S = 2.0
READ_POLL_S = 0.05


class DeviceError(RuntimeError):
    """An instrument did not do what was asked; the message names role, port and what happened."""


class DeviceTimeout(DeviceError):
    pass


class DeviceUnavailable(DeviceError):
    """The port is not open (pulled cable, wrong path, reconnecting)."""


class DeviceRefused(DeviceError):
    """The instrument answered that it refuses the command."""


def resolve_usb_serial(usb_serial: str) -> str:
    """The device path of the USB serial adapter with this serial number."""
    found = [
        comport.device
        for comport in serial.tools.list_ports.comports()
        if comport.serial_number == usb_serial
    ]
    if not found:
        raise DeviceUnavailable(
            f"no USB serial adapter with serial number {usb_serial} is plugged in"
        )
    if len(found) > 1:
        raise DeviceUnavailable(f"USB serial number {usb_serial} is reported by {', '.join(found)}")
    path: str = found[0]
    return path


@dataclass
class _Pending:
    match: Callable[[Any], bool]
    future: asyncio.Future[Any]
    loop: asyncio.AbstractEventLoop


class SerialPort:
    """A port, its decoder and its reader thread. Shared by every driver on the same bus."""

    def __init__(
        self,
        where: str,
        parse: Callable[[bytes], Parsed[Any]],
        *,
        baud: int,
        usb_serial: str | None = None,
        fail_after_s: float = 30.0,
    ) -> None:
        self.where = where  # as configured: path, URL, or usb_serial=...
        self.usb_serial = usb_serial
        self.baud = baud
        self.fail_after_s = fail_after_s
        self.decoder = Decoder(parse)
        self.state: DeviceState = "reconnecting"
        self.error: str | None = None
        self.reconnects = 0
        self.last_frame_utc: dt.datetime | None = None
        self._listeners: list[Callable[[Any, dt.datetime], None]] = []
        self._serial: serial.SerialBase | None = None
        self._lock = threading.Lock()  # guards _serial, _pending
        self._pending: list[_Pending] = []
        self._stop = threading.Event()
        self._connected = threading.Event()
        self._thread: threading.Thread | None = None
        self._writer: concurrent.futures.ThreadPoolExecutor | None = None
        self._request_lock: asyncio.Lock | None = None
        self._users = 0
        self.bytes_read = 0
        # Addresses (family A, B) or axes (family D) of the instruments the drivers on this port
        # own.
        self.owned: set[int] = set()
        self.wrong_address = 0
        self.foreign_senders: set[int] = set()

    # --- life cycle -----------------------------------------------------------------------------

    def add_listener(self, fn: Callable[[Any, dt.datetime], None]) -> None:
        """fn(message, received_utc) runs in the reader thread for every message; keep it short."""
        self._listeners.append(fn)

    def start(self) -> None:
        self._users += 1
        if self._thread is None:
            self._thread = threading.Thread(
                target=self._run, name=f"port {self.where}", daemon=True
            )
            self._thread.start()

    def stop(self) -> None:
        self._users -= 1
        if self._users > 0 or self._thread is None:
            return
        self._stop.set()
        self._thread.join(timeout=5)
        self._thread = None
        self._close()
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.shutdown(wait=False)

    def wait_connected(self, timeout_s: float) -> bool:
        return self._connected.wait(timeout_s)

    def _open(self) -> serial.SerialBase:
        path = resolve_usb_serial(self.usb_serial) if self.usb_serial else self.where
        is_url = "://" in path
        ser = serial.serial_for_url(path, baudrate=self.baud, timeout=READ_POLL_S, do_not_open=True)
        if not is_url:
            ser.exclusive = True  # one owner per port, also against other processes
            ser.write_timeout = 1.0  # (the rfc2217 handler refuses a write timeout)
        ser.open()
        return ser

    def _close(self) -> None:
        with self._lock:
            ser, self._serial = self._serial, None
        self._connected.clear()
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001 - a port that is gone may fail to close; it is closed for us
                pass

    def _run(self) -> None:
        backoff = BACKOFF_FIRST_S
        down_since = time.monotonic()
        ever = False
        while not self._stop.is_set():
            try:
                ser = self._open()
            except Exception as exc:  # noqa: BLE001 - every failure to open means: try again later
                self.error = f"cannot open {self.where}: {exc}"
                if time.monotonic() - down_since > self.fail_after_s:
                    self.state = "failed"
                self._stop.wait(backoff)
                backoff = min(backoff * 2, BACKOFF_MAX_S)
                continue
            with self._lock:
                self._serial = ser
            self.decoder.reset()
            if ever:
                self.reconnects += 1
            ever = True
            self.state, self.error, backoff = "connected", None, BACKOFF_FIRST_S
            self._connected.set()
            self._read_until_failure(ser)
            self._close()
            if self._stop.is_set():
                break
            self.state = "reconnecting"
            down_since = time.monotonic()
            self._fail_pending(DeviceUnavailable(f"port {self.where} went away: {self.error}"))
        self._fail_pending(DeviceUnavailable(f"port {self.where} is closed"))

    def _read_until_failure(self, ser: serial.SerialBase) -> None:
        while not self._stop.is_set():
            try:
                data = ser.read(max(1, ser.in_waiting))
            except Exception as exc:  # noqa: BLE001 - pyserial raises SerialException or OSError when the port goes
                self.error = str(exc) or type(exc).__name__
                return
            if not data:
                continue
            self.bytes_read += len(data)
            messages = self.decoder.feed(data)
            if messages:
                self._deliver(messages)

    def own(self, address: int) -> None:
        """A driver on this port answers to `address` (its axis, for a controller)."""
        self.owned.add(address)

    def _deliver(self, messages: list[Any]) -> None:
        now = dt.datetime.now(dt.UTC)
        self.last_frame_utc = now
        for msg in messages:
            sender = getattr(msg, "address", getattr(msg, "axis", None))
            if sender is not None and self.owned and sender not in self.owned:
                self.wrong_address += 1  # a good frame, from an instrument nobody here asked
                self.foreign_senders.add(sender)
                continue
            for fn in self._listeners:
                fn(msg, now)
            with self._lock:
                hit = next((waiting for waiting in self._pending if waiting.match(msg)), None)
                if hit is not None:
                    self._pending.remove(hit)
            if hit is not None:
                hit.loop.call_soon_threadsafe(_resolve, hit.future, msg)

    def _fail_pending(self, exc: Exception) -> None:
        with self._lock:
            pending, self._pending = self._pending, []
        for waiting in pending:
            waiting.loop.call_soon_threadsafe(_fail, waiting.future, exc)

    # --- requests -------------------------------------------------------------------------------

    def _write(self, data: bytes) -> None:
        with self._lock:
            ser = self._serial
        if ser is None:
            raise DeviceUnavailable(
                f"port {self.where} is not open "
                f"({self.state}{': ' + self.error if self.error else ''})"
            )
        try:
            ser.write(data)
        except Exception as exc:  # noqa: BLE001
            raise DeviceUnavailable(f"port {self.where}: write failed: {exc}") from None

    async def _write_off_loop(self, data: bytes) -> None:
        """A write in the port's own thread: a stuck adapter blocks it, not the loop, and a write
        never waits for a worker of the shared pool (busy with database work under load)."""
        if self._writer is None:
            self._writer = concurrent.futures.ThreadPoolExecutor(
                1, thread_name_prefix=f"write {self.where}"
            )
        await asyncio.get_running_loop().run_in_executor(self._writer, self._write, data)

    async def send(self, data: bytes) -> None:
        """A command that is not answered (family D set commands)."""
        async with self._lock_for_requests():
            await self._write_off_loop(data)

    async def request(
        self, data: bytes, match: Callable[[Any], bool], timeout_s: float, what: str
    ) -> Any:
        """Write a request and wait for the first message `match` accepts; one request in flight per
        port."""
        async with self._lock_for_requests():
            loop = asyncio.get_running_loop()
            pending = _Pending(match, loop.create_future(), loop)
            with self._lock:
                self._pending.append(pending)
            try:
                # (wait_for may swallow a cancellation before 3.12)
                async with asyncio.timeout(timeout_s):
                    await self._write_off_loop(data)
                    return await pending.future
            except TimeoutError:
                if pending.future.done() and not pending.future.cancelled():
                    # the answer came in time, but the loop ran the timer before this task saw it
                    # (a loop held up past the deadline runs both in one pass)
                    return pending.future.result()
                raise DeviceTimeout(
                    f"{what}: no answer on {self.where} within {timeout_s:g} s"
                ) from None
            finally:
                with self._lock:
                    if pending in self._pending:
                        self._pending.remove(pending)
                if not pending.future.done():
                    pending.future.cancel()

    def _lock_for_requests(self) -> asyncio.Lock:
        if self._request_lock is None:
            self._request_lock = asyncio.Lock()
        return self._request_lock


def _resolve(fut: asyncio.Future[Any], value: Any) -> None:
    if not fut.done():
        fut.set_result(value)


def _fail(fut: asyncio.Future[Any], exc: Exception) -> None:
    if not fut.done():
        fut.set_exception(exc)


class PortRegistry:
    """One SerialPort per place: drivers on one RS-485 bus share it; nothing else may."""

    def __init__(self) -> None:
        self._ports: dict[str, tuple[SerialPort, str]] = {}

    def get(
        self, where: str, parse: Callable[[bytes], Parsed[Any]], family: str, **kwargs: Any
    ) -> SerialPort:
        if where in self._ports:
            port, fam = self._ports[where]
            if fam != family or family != "rs485":
                raise DeviceError(f"port {where} is already owned by another instrument")
            return port
        port = SerialPort(where, parse, **kwargs)
        self._ports[where] = (port, family)
        return port
