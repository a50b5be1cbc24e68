"""Port transport beyond device paths: instruments found by USB serial number, instruments behind a
TCP serial server (socket://), and a port that never opens (state failed, message naming it)."""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from types import SimpleNamespace

import pytest

from service.clock import Clock
from service.instruments import controller
from service.instruments.bench_config import parse_bench_config
from service.instruments.drivers import ControllerAxis
from service.instruments.sim.firmware import ControllerFirmware
from service.instruments.sim.world import Axis
from service.instruments.transport import DeviceUnavailable, SerialPort, resolve_usb_serial
from service.instruments.wiring import open_bench
from tests.helpers.instruments import eventually_async
from tests.helpers.waiting import eventually

# the ports are pseudo-terminals (device paths, USB names, servers in front)
pytestmark = pytest.mark.pty


def test_a_usb_serial_number_names_the_adapter_wherever_it_is_plugged(stage_sim, monkeypatch):
    ports = [
        SimpleNamespace(device="/dev/ttyS0", serial_number=None),
        SimpleNamespace(device=stage_sim.port_path("stage"), serial_number="FT5XYZ12"),
    ]
    monkeypatch.setattr("serial.tools.list_ports.comports", lambda: ports)
    assert resolve_usb_serial("FT5XYZ12") == stage_sim.port_path("stage")
    with pytest.raises(DeviceUnavailable, match="no USB serial adapter with serial number NOPE"):
        resolve_usb_serial("NOPE")
    text = stage_sim.toml.replace(
        f'port = "{stage_sim.port_path("stage")}"', 'usb_serial = "FT5XYZ12"'
    )
    config = parse_bench_config(__import__("tomllib").loads(text)).bench()

    async def main():
        dev = open_bench(config, stage_sim.clock)
        await dev.start()
        try:
            assert (await dev.stage.identify()).model == "SC-200SIM"
            assert dev.stage.status.port == "usb_serial=FT5XYZ12"
        finally:
            await dev.close()

    asyncio.run(main())


class _TcpController(threading.Thread):
    """A controller behind a TCP serial server: the same firmware, bytes over a socket."""

    def __init__(self, clock: Clock) -> None:
        super().__init__(daemon=True)
        self.axis = Axis(clock, 0.001, 20_000, None, None)
        self.firmware = ControllerFirmware({3: self.axis}, model="RT-360SIM")
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.stop = threading.Event()

    def run(self) -> None:
        conn, _ = self.server.accept()
        conn.settimeout(0.05)
        with conn:
            while not self.stop.is_set():
                try:
                    data = conn.recv(4096)
                except TimeoutError:
                    continue
                if not data:
                    return
                for answer in self.firmware.handle(data):
                    conn.sendall(answer)


def _with_tcp_table(timeout_s: float, body, speed: float = 1.0) -> None:  # type: ignore[no-untyped-def]
    """Run `body(table, server)` against a rotary table behind a TCP serial server."""
    clock = Clock(speed)
    server = _TcpController(clock)
    server.start()

    async def main():
        port = SerialPort(f"socket://127.0.0.1:{server.port}", controller.parse_answers, baud=57600)
        table = ControllerAxis("rotary_table", port, clock, timeout_s, axis=3, pulse_deg=0.001)
        await table.start()
        try:
            await body(table, server)
        finally:
            await table.close()

    try:
        asyncio.run(main())
    finally:
        server.stop.set()
        server.server.close()


def test_an_instrument_behind_a_tcp_serial_server():
    async def body(table, server):
        assert (await table.identify()).model == "RT-360SIM"
        await table.move_to_deg(90.0)
        await table.wait_until_idle(60)
        assert await table.position_deg() == pytest.approx(90.0)
        assert server.axis.deg == pytest.approx(90.0)

    _with_tcp_table(1.0, body, speed=20.0)


def test_a_port_that_never_opens_is_failed_and_says_why(tmp_path):
    async def main():
        port = SerialPort(
            str(tmp_path / "ttyUSB9"), controller.parse_answers, baud=57600, fail_after_s=0.2
        )
        axis = ControllerAxis("stage", port, Clock(1.0), 0.2, axis=1, pulse_deg=0.0005)
        await axis.start()
        try:
            assert axis.status.state in ("reconnecting", "failed")
            await eventually_async(lambda: axis.status.state == "failed", "state failed")
            assert "ttyUSB9" in axis.status.error
            with pytest.raises(DeviceUnavailable, match="is not open"):
                await axis.position_pulses()
        finally:
            await axis.close()

    asyncio.run(main())


class _NoModemLines:
    """A pseudo-terminal has no modem lines to report; the server asks for them."""

    cts = dsr = ri = cd = False

    def __init__(self, port) -> None:
        object.__setattr__(self, "_port", port)

    def __getattr__(self, name):
        return getattr(self._port, name)

    def __setattr__(self, name, value) -> None:
        if name not in ("rts", "dtr", "break_condition"):
            setattr(self._port, name, value)


class _Rfc2217Server(threading.Thread):
    """An RFC 2217 serial server in front of a simulated instrument's port (pyserial's
    PortManager)."""

    def __init__(self, device: str) -> None:
        super().__init__(daemon=True)
        import serial

        self.serial = serial.serial_for_url(device, timeout=0.05)
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.stop = threading.Event()

    def run(self) -> None:
        import serial.rfc2217

        conn, _ = self.server.accept()
        conn.settimeout(0.05)
        manager = serial.rfc2217.PortManager(
            _NoModemLines(self.serial), SimpleNamespace(write=conn.sendall)
        )
        with conn:
            while not self.stop.is_set():
                data = self.serial.read(self.serial.in_waiting or 1)
                if data:
                    conn.sendall(b"".join(manager.escape(data)))
                try:
                    got = conn.recv(4096)
                except TimeoutError:
                    continue
                if not got:
                    return
                self.serial.write(b"".join(manager.filter(got)))


@pytest.mark.filterwarnings("ignore:set(Daemon|Name)\\(\\) is deprecated:DeprecationWarning")
def test_an_instrument_behind_an_rfc2217_server(stage_sim):
    server = _Rfc2217Server(stage_sim.port_path("stage"))
    server.start()

    async def main():
        port = SerialPort(
            f"rfc2217://127.0.0.1:{server.port}", controller.parse_answers, baud=57600
        )
        axis = ControllerAxis("stage", port, stage_sim.clock, 2.0, axis=2, pulse_deg=0.0005)
        await axis.start()
        try:
            assert (await axis.identify()).model == "SC-200SIM"
            await axis.move_to_deg(-1.5)
            await axis.wait_until_idle(60)
            assert await axis.position_deg() == pytest.approx(-1.5)
            assert stage_sim.world.pose_deg[1] == pytest.approx(-1.5)
        finally:
            await axis.close()

    try:
        asyncio.run(main())
    finally:
        server.stop.set()
        server.join(5)
        server.serial.close()
        server.server.close()


def test_requests_do_not_wait_for_the_shared_worker_pool():
    """Every worker of the loop's default pool held (as database writes waiting for a lock would
    hold them): a request still goes out and is answered, because writes use the port's own
    thread."""

    async def body(table, _server):
        loop = asyncio.get_running_loop()
        release = threading.Event()
        held = [loop.run_in_executor(None, release.wait, 30) for _ in range(64)]
        try:
            assert (await table.identify()).model == "RT-360SIM"
        finally:
            release.set()
            await asyncio.gather(*held)

    _with_tcp_table(1.0, body)


def test_an_answer_in_time_is_kept_when_the_event_loop_runs_late():
    """The loop held up past a request's deadline (a blocking call elsewhere): the answer that came
    meanwhile is returned, not a timeout."""

    async def body(table, _server):
        frames = table.port.decoder.stats.frames
        asked = asyncio.get_running_loop().create_task(table.identify())
        await asyncio.sleep(0)  # the request runs up to its write, in the port's thread
        # the loop blocked (eventually sleeps, it does not await) past the 0.3 s timeout and until
        # the reader thread has parsed the answer
        blocked_from = time.monotonic()
        eventually(
            lambda: (
                time.monotonic() - blocked_from >= 0.6 and table.port.decoder.stats.frames != frames
            ),
            timeout_s=30,
            what="the answer parsed, the event loop held 0.6 s",
        )
        assert (await asked).model == "RT-360SIM"
        assert table.timeouts == 0

    _with_tcp_table(0.3, body)
