"""Live streams over WebSocket against a real uvicorn server on the simulated stage bench (sped up).

The app runs in-process (a server thread) so the tests can look at the producer's client registry
and the job manager's watchers after clients go.
"""

from __future__ import annotations

import asyncio
import base64
import datetime as dt
import json
import os
import socket
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import httpx
import pytest
import uvicorn
import websockets
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from service.api.app import create_app
from service.api.limits import STREAM_HELD_BYTES, WEBSOCKET_IMPLEMENTATION
from service.commands.serve import bind_socket
from service.config import Settings
from tests.helpers.running_service import free_port
from tests.helpers.waiting import eventually

SPEED = 10.0
SLOW_CLOSE_S = 2.0
QUEUE = 40
READING_KEYS = {
    "seq",
    "time_utc",
    "type",
    "raw",
    "table_tilt",
    "reference_tilt",
    "in_calibrated_range",
    "stage",
    "temp_c",
    "calibration",
}
SNAPSHOT_KEYS = {
    "type",
    "seq",
    "time_utc",
    "bench",
    "rate_hz",
    "raw",
    "table_tilt",
    "reference_tilt",
    "in_calibrated_range",
    "stage",
    "temp_c",
    "calibration",
    "history",
}


@dataclass
class Daemon:
    app: object
    base: str
    ws: str
    token: str

    def url(self, path: str, **query: object) -> str:
        q = {"token": self.token, **query}
        return f"{self.ws}{path}?" + "&".join(f"{k}={v}" for k, v in q.items() if v is not None)

    @property
    def hub(self):  # type: ignore[no-untyped-def]
        return self.app.state.streams  # type: ignore[attr-defined]


@pytest.fixture(scope="module")
def daemon(tmp_path_factory) -> Iterator[Daemon]:
    data = tmp_path_factory.mktemp("streams")
    settings = Settings(
        data_dir=data,
        sim_speed=SPEED,
        stream_slow_close_s=SLOW_CLOSE_S,
        stream_queue_size=QUEUE,
        sim_transport="loopback",
    )  # in process: the instruments on in-memory lines
    app = create_app(settings)
    port = free_port()
    # as `tiltlab serve` makes it: every connection's send buffer bounded
    sock = bind_socket("127.0.0.1", port)
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", ws=WEBSOCKET_IMPLEMENTATION))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    eventually(lambda: server.started, timeout_s=60, every_s=0.05, what="server started")
    token = (data / "admin.token").read_text().strip()
    try:
        yield Daemon(app, f"http://127.0.0.1:{port}", f"ws://127.0.0.1:{port}", token)
    finally:
        producers = list(app.state.streams.producers.values())  # type: ignore[attr-defined]
        server.should_exit = True
        thread.join(30)
        sock.close()
        assert not thread.is_alive()
        assert producers and not any(p.running for p in producers), "a producer outlived the daemon"


class RawClient:
    """A WebSocket client on a plain socket with a small receive buffer, reading only when asked."""

    def __init__(self, daemon: Daemon, path: str) -> None:
        self.sock = socket.socket()
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        self.sock.settimeout(20)
        self.sock.connect(("127.0.0.1", int(daemon.base.rsplit(":", 1)[1])))
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade"
            f"\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode()
        )
        self.buf = b""
        self.received = 0
        while b"\r\n\r\n" not in self.buf:
            self.buf += self._recv()
        head, self.buf = self.buf.split(b"\r\n\r\n", 1)
        assert head.startswith(b"HTTP/1.1 101"), head
        self.received = len(self.buf)  # bytes of frames received so far

    def _recv(self) -> bytes:
        data = self.sock.recv(65536)
        assert data, "connection closed without a close frame"
        self.received += len(data)
        return data

    def _take(self, n: int) -> bytes:
        while len(self.buf) < n:
            self.buf += self._recv()
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def message(self) -> dict:
        """The next text message (parsed) or {"type": "close", "code", "reason"}."""
        b0, b1 = self._take(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack("!H", self._take(2))[0]
        elif n == 127:
            n = struct.unpack("!Q", self._take(8))[0]
        payload = self._take(n)
        if b0 & 0x0F == 0x8:
            return {
                "type": "close",
                "code": struct.unpack("!H", payload[:2])[0],
                "reason": payload[2:].decode(),
            }
        assert b0 & 0x0F == 0x1, b0
        return json.loads(payload)


async def _closed_with(url: str) -> tuple[int, str]:
    """Connect and read until closed; the close code and reason."""
    async with connect(url) as ws:
        with pytest.raises(ConnectionClosed):
            while True:
                await asyncio.wait_for(ws.recv(), 10)
        assert ws.close_code is not None
        return ws.close_code, ws.close_reason or ""


def test_bad_requests_are_refused_with_a_reason(daemon: Daemon) -> None:
    cases = [
        (daemon.url("/ws/readings", token=None).replace("token=&", ""), "token"),
        (daemon.url("/ws/readings").replace(daemon.token, "tl_not_a_token"), "token"),
        (daemon.url("/ws/readings", rate_hz="abc"), "rate_hz"),
        (daemon.url("/ws/readings", rate_hz=0), "rate_hz"),
        (daemon.url("/ws/readings", rate_hz=-5), "rate_hz"),
        (daemon.url("/ws/readings", history_s=99999), "history_s"),
        (daemon.url("/ws/readings", bench="no-such-bench"), "bench"),
        (daemon.url("/ws/jobs/99999"), "id"),
        (daemon.url("/ws/jobs/99999").replace(daemon.token, ""), "token"),
    ]

    async def run() -> None:
        for url, field in cases:
            code, reason = await _closed_with(url)
            assert code == 1008 and reason.startswith(f"{field}:"), (url, code, reason)

    asyncio.run(run())
    eventually(
        lambda: daemon.hub.client_count() == 0, timeout_s=20, every_s=0.05, what="registry empty"
    )


def test_sequence_has_no_gaps_and_rate_is_clamped(daemon: Daemon) -> None:
    sensor_hz = daemon.hub.producers["sim-stage"].sensor_rate_hz

    async def run() -> None:
        async with connect(daemon.url("/ws/readings", rate_hz=10_000, history_s=1)) as ws:
            snap = json.loads(await asyncio.wait_for(ws.recv(), 10))
            assert set(snap) == SNAPSHOT_KEYS and snap["type"] == "snapshot" and snap["seq"] == 0
            # clamped to the sensors' rate
            assert snap["bench"] == "sim-stage" and snap["rate_hz"] == sensor_hz
            for expected in range(1, 201):
                m = json.loads(await asyncio.wait_for(ws.recv(), 10))
                assert m["seq"] == expected and m["type"] == "reading", m
                assert set(m) == READING_KEYS
                assert set(m["raw"]) == {"measurement_sensor", "reference_sensor"}
                # null while a sensor is silent (a loaded machine lags the simulation)
                for pair in m["raw"].values():
                    assert pair is None or set(pair) == {"x_deg", "y_deg"}
                assert set(m["stage"]) == {"x_deg", "y_deg", "moving"}
            assert daemon.hub.client_count() == 1

    asyncio.run(run())
    eventually(
        lambda: daemon.hub.client_count() == 0,
        timeout_s=20,
        every_s=0.05,
        what="registry empty after a normal close",
    )


def test_slow_client_gets_drops_then_closed_others_see_no_gap(daemon: Daemon) -> None:
    fast_seqs: list[list[int]] = [[], []]
    fast_types: set[str] = set()
    stop = asyncio.Event()

    async def fast(i: int) -> None:
        async with connect(daemon.url("/ws/readings", history_s=1)) as ws:
            while not stop.is_set():
                m = json.loads(await asyncio.wait_for(ws.recv(), 10))
                fast_types.add(m["type"])
                fast_seqs[i].append(m["seq"])

    async def slow() -> tuple[list[dict], int, str]:
        # A raw socket: a client library keeps reading into its own buffers; this one reads only
        # when told.
        raw = RawClient(daemon, "/ws/readings?history_s=1&token=" + daemon.token)
        try:
            got = [raw.message()]
            # Stop reading until the server's queue for this client overflows ...
            # (the waits in a thread of their own: the reading clients go on in this event loop)
            t0 = time.monotonic()
            await asyncio.to_thread(
                eventually,
                lambda: any(
                    c.dropped_total for c in list(daemon.hub.producers["sim-stage"].clients)
                ),
                timeout_s=40,
                every_s=0.05,
                what="the stuck client's queue overflowing",
            )
            # ... then read again: when room returns the server says how many were dropped.
            while not any(m["type"] == "dropped" for m in got):
                got.append(raw.message())
            # Now stop reading altogether: the server must give up on this client.
            await asyncio.to_thread(
                eventually,
                lambda: daemon.hub.client_count() <= 2,
                timeout_s=80 - (time.monotonic() - t0),  # 80 s from t0 for both waits
                every_s=0.1,
                what="the stuck client closed",
            )
            while True:
                m = raw.message()
                if m.get("type") == "close":
                    return got, m["code"], m["reason"]
                got.append(m)
        finally:
            raw.sock.close()

    async def run() -> tuple[list[dict], int, str]:
        tasks = [asyncio.create_task(fast(0)), asyncio.create_task(fast(1))]
        # both reading clients connected before the stuck one (waited for in a thread: they
        # connect in this event loop)
        await asyncio.to_thread(
            eventually,
            lambda: daemon.hub.client_count() >= 2,
            timeout_s=30,
            every_s=0.02,
            what="the reading clients connected",
        )
        try:
            return await slow()
        finally:
            stop.set()
            await asyncio.gather(*tasks)

    got, code, reason = asyncio.run(run())
    assert code == 1013 and reason.startswith("too slow"), (code, reason)
    # The slow client's sequence: every gap is accounted for by the dropped message that follows it.
    expect = 0
    pending_gap = 0
    for m in got:
        if m["seq"] > expect:
            pending_gap += m["seq"] - expect
        assert m["seq"] >= expect, "sequence numbers went back"
        if m["type"] == "dropped":
            assert m["count"] == pending_gap, (m, pending_gap)
            pending_gap = 0
        expect = m["seq"] + 1
    assert any(m["type"] == "dropped" and m["count"] > 0 for m in got)
    # The clients that kept up lost nothing.
    assert fast_types <= {"snapshot", "reading"}
    for seqs in fast_seqs:
        assert len(seqs) > 50 and seqs == list(range(len(seqs))), "a fast client saw a gap"
    eventually(
        lambda: daemon.hub.client_count() == 0,
        timeout_s=20,
        every_s=0.05,
        what="registry empty after the slow client was closed",
    )


def test_reconnect_gets_a_snapshot_with_history(daemon: Daemon) -> None:
    async def run() -> tuple[dict, dict]:
        async with connect(daemon.url("/ws/readings", rate_hz=5)) as ws:
            for _ in range(5):
                await asyncio.wait_for(ws.recv(), 10)
            last = json.loads(await asyncio.wait_for(ws.recv(), 10))
        async with connect(daemon.url("/ws/readings", rate_hz=5, history_s=30)) as ws:
            snap = json.loads(await asyncio.wait_for(ws.recv(), 10))
        return last, snap

    last, snap = asyncio.run(run())
    assert snap["type"] == "snapshot" and snap["seq"] == 0 and snap["rate_hz"] == 5
    hist = snap["history"]
    assert len(hist) >= 2
    assert all(
        "seq" not in h
        and set(h) == READING_KEYS - {"seq", "calibration"}
        and h["type"] == "reading"
        for h in hist
    )
    times = [h["time_utc"] for h in hist]
    assert times == sorted(times) and times[-1] <= snap["time_utc"]
    # what the first connection saw is history now: the history spans its time, and, being decimated
    # to 5 Hz of bench time, its newest entry is at most one period (real time: 0.2 s / SPEED)
    # before it
    at = lambda t: dt.datetime.fromisoformat(t.replace("Z", "+00:00"))  # noqa: E731
    assert at(times[0]) <= at(last["time_utc"])
    assert at(times[-1]) >= at(last["time_utc"]) - dt.timedelta(seconds=0.2 / SPEED + 0.005), (
        times[-1],
        last,
    )
    eventually(
        lambda: daemon.hub.client_count() == 0,
        timeout_s=20,
        every_s=0.05,
        what="registry empty after reconnects",
    )


def test_job_stream_follows_a_calibration_to_its_end(daemon: Daemon) -> None:
    h = {"Authorization": f"Bearer {daemon.token}"}
    body = {
        "procedure": "stage-grid",
        "method": "kinematic",
        "grid": {"x_deg": [-2.0, 2.0], "y_deg": [-2.0, 2.0], "n_x": 3, "n_y": 3},
        "samples_per_point": 4,
        "validation": {"n_points": 1},
        # a generous settling time: a loaded machine lags the sped-up simulation (bench seconds)
        "settle": {"tolerance_deg": 0.005, "window_s": 0.5, "timeout_s": 600},
    }
    r = httpx.post(f"{daemon.base}/calibrations", headers=h, json=body, timeout=30)
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]

    async def follow() -> tuple[list[dict], int]:
        msgs: list[dict] = []
        async with connect(daemon.url(f"/ws/jobs/{job_id}")) as ws:
            with pytest.raises(ConnectionClosed):
                while True:
                    msgs.append(json.loads(await asyncio.wait_for(ws.recv(), 60)))
            return msgs, ws.close_code or 0

    msgs, code = asyncio.run(follow())
    assert code == 1000
    assert [m["seq"] for m in msgs] == list(range(len(msgs)))
    assert msgs[0]["type"] == "snapshot" and msgs[0]["job"]["id"] == job_id
    assert msgs[-1]["type"] == "end" and [m["type"] for m in msgs].count("end") == 1
    final = httpx.get(f"{daemon.base}/calibrations/{job_id}", headers=h, timeout=30).json()
    assert msgs[-1]["job"] == final and final["state"] == "succeeded", final
    points = msgs[0]["points"] + [m["point"] for m in msgs if m["type"] == "point"]
    # 9 grid points and 1 validation point
    assert sorted(p["index"] for p in points) == list(range(10))
    for p in points:
        assert {"index", "x_deg", "y_deg", "reference_sensor", "measurement_sensor"} <= set(p)
        assert p["measurement_sensor"]["n_samples"] >= 1
    done = [m["job"]["progress"]["points_done"] for m in msgs if m["type"] in ("job", "end")]
    assert done == sorted(done) and done[-1] == 10
    assert any(m["type"] == "job" and m["job"]["state"] == "running" for m in msgs)

    async def after_end() -> tuple[list[dict], int]:
        async with connect(daemon.url(f"/ws/jobs/{job_id}")) as ws:
            got = [json.loads(await asyncio.wait_for(ws.recv(), 10)) for _ in range(2)]
            with pytest.raises(ConnectionClosed):
                await asyncio.wait_for(ws.recv(), 10)
            return got, ws.close_code or 0

    got, code = asyncio.run(after_end())
    assert [m["type"] for m in got] == ["snapshot", "end"] and code == 1000
    assert len(got[0]["points"]) == 10
    eventually(
        lambda: daemon.app.state.jobs.events.watcher_count() == 0,  # type: ignore[attr-defined]
        timeout_s=20,
        every_s=0.05,
        what="no job watchers left",
    )


def test_dropped_connections_leave_nothing_behind(daemon: Daemon) -> None:
    async def run() -> None:
        conns = [await connect(daemon.url("/ws/readings", rate_hz=5)) for _ in range(5)]
        for ws in conns:
            await asyncio.wait_for(ws.recv(), 10)
        assert daemon.hub.client_count() == 5
        for ws in conns[:3]:
            await ws.close()
        for ws in conns[3:]:  # gone without a close handshake
            ws.transport.abort()

    asyncio.run(run())
    eventually(
        lambda: daemon.hub.client_count() == 0,
        timeout_s=20,
        every_s=0.05,
        what="registry empty after aborted connections",
    )
    assert websockets.__version__  # the client library the tests speak through


def test_a_client_that_never_reads_is_closed_in_time_while_a_reader_sees_no_gap(
    daemon: Daemon,
) -> None:
    """The bound of docs/api.md: the daemon holds at most STREAM_HELD_BYTES for a client that reads
    nothing, and once its send has waited TILTLAB_STREAM_SLOW_CLOSE_S it is closed (1013)."""
    seqs: list[int] = []
    received = [0]
    stop = asyncio.Event()

    async def reader() -> None:
        async with connect(
            daemon.url("/ws/readings", token=None, history_s=1),
            subprotocols=[f"bearer.{daemon.token}"],
        ) as ws:  # type: ignore[list-item]
            while not stop.is_set():
                text = await asyncio.wait_for(ws.recv(), 10)
                received[0] += len(text)
                seqs.append(json.loads(text)["seq"])

    async def stalled() -> tuple[float, float, RawClient]:
        # never reads a message
        raw = RawClient(daemon, "/ws/readings?history_s=1&token=" + daemon.token)
        while daemon.hub.client_count() < 2:  # registered just after the handshake
            await asyncio.sleep(0.01)
        t0 = time.monotonic()
        bytes0 = received[0]
        rcvbuf = raw.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        while daemon.hub.client_count() > 1:
            elapsed = time.monotonic() - t0
            rate = (received[0] - bytes0) / max(elapsed, 1e-3)  # the stream's bytes per real second
            # documented: closed SLOW_CLOSE_S after the daemon's buffers and the client's are full;
            # a grace for a loaded machine, far below what unbounded (megabyte) buffers would take
            allowed = 1.5 * (SLOW_CLOSE_S + (STREAM_HELD_BYTES + rcvbuf) / max(rate, 1.0)) + 3.0
            assert elapsed < allowed or rate == 0, (
                f"not closed after {elapsed:.1f} s ({rate:.0f} B/s)"
            )
            await asyncio.sleep(0.05)
        return time.monotonic() - t0, (received[0] - bytes0) / (time.monotonic() - t0), raw

    async def run() -> tuple[float, float, RawClient]:
        task = asyncio.create_task(reader())
        while len(seqs) < 5:
            await asyncio.sleep(0.05)
        try:
            return await stalled()
        finally:
            stop.set()
            await task

    closed_after_s, rate, raw = asyncio.run(run())
    assert closed_after_s > SLOW_CLOSE_S  # its send waited the whole slow-close time first
    # what the daemon had handed over before giving up: at most its buffers' worth, then the close
    try:
        got: list[dict] = []
        raw.sock.settimeout(10)
        while True:
            m = raw.message()
            if m["type"] == "close":
                break
            got.append(m)
    finally:
        raw.sock.close()
    assert m["code"] == 1013 and m["reason"].startswith("too slow"), m
    held = raw.received
    assert got and got[0]["type"] == "snapshot" and [x["seq"] for x in got] == list(range(len(got)))
    assert held <= STREAM_HELD_BYTES + 4 * 4096 + 2048, (
        f"{held} bytes were held for a client reading nothing"
    )
    assert seqs == list(range(len(seqs))) and len(seqs) > 20, "the reading client saw a gap"
    eventually(
        lambda: daemon.hub.client_count() == 0, timeout_s=20, every_s=0.05, what="registry empty"
    )
