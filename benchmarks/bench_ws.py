"""Reading stream under load: N WebSocket clients at 50 Hz on one bench, plus one client that never
reads.

Starts a simulated stage bench whose sensors output 50 Hz (pseudo-terminals, in this process) and
`tiltlab serve --bench-config` on it in a subprocess, then connects the clients and reports messages
lost by the reading clients (seq gaps; target 0), delivery latency p50/p99 (message time_utc to
receipt, same machine clock), and the daemon's CPU time from /proc/<pid>/stat.

    .venv/bin/python benchmarks/bench_ws.py                 # 100 clients, 60 s
    .venv/bin/python benchmarks/bench_ws.py --seconds 10
    .venv/bin/python benchmarks/bench_ws.py --ramp          # add clients until they wait or lose
    .venv/bin/python benchmarks/bench_ws.py --ramp --event-loop asyncio   # asyncio, not uvloop

The ramp's saturation point is the message rate where the reading clients first wait: the step at
which they receive less than 95 % of what they asked for (clients x rate_hz), or lose a message.

    .venv/bin/python benchmarks/bench_ws.py --ramp --client sweep   # cheapest: see `sweep_run`

Reading clients cost CPU too, and on a small machine they share it with the daemon: the saturation
point found is the lower of the daemon's and the clients'. `--client sweep` is the cheapest way of
reading every message that was found (it prints its own share of a core), so the point it
finds is the daemon's.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import datetime as dt
import json
import multiprocessing
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
from websockets.asyncio.client import connect

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from service.clock import Clock  # noqa: E402
from service.instruments.sim import start_simulated_bench  # noqa: E402
from service.io.datasets import write_text_atomic  # noqa: E402
from tests.helpers.running_service import free_port  # noqa: E402

TICK = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK  # utime + stime


class Stats:
    def __init__(self) -> None:
        self.lost = 0
        self.received = 0
        self.latency: list[float] = []
        self.clients_losing: set[int] = set()


async def reader(i: int, url: str, stats: Stats, stop: asyncio.Event) -> None:
    async with connect(url, max_size=None) as ws:
        json.loads(await ws.recv())  # snapshot
        last = 0
        while not stop.is_set():
            try:
                text = await asyncio.wait_for(ws.recv(), 1.0)
            except TimeoutError:
                continue
            now = time.time()
            m = json.loads(text)
            if m["seq"] != last + 1 or m["type"] == "dropped":
                stats.lost += m["count"] if m["type"] == "dropped" else m["seq"] - last - 1
                stats.clients_losing.add(i)
            last = m["seq"]
            if m["type"] == "reading":
                stats.received += 1
                stats.latency.append(now - dt.datetime.fromisoformat(m["time_utc"]).timestamp())


class RawReader(asyncio.Protocol):
    """A reading client at the cost of a few bytes operations per message (the `websockets` client
    costs more CPU per message than the daemon itself: one process of them could not show where the
    daemon saturates). It reads every frame, checks seq from the message's first bytes
    (`{"seq":N,...`), and parses one message in 10 for its time."""

    def __init__(self, i: int, path: str, stats: Stats) -> None:
        self.i, self.path, self.stats = i, path, stats
        self.buf = bytearray()
        self.upgraded = False
        self.last = -1
        self.closed = asyncio.get_running_loop().create_future()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport
        key = base64.b64encode(os.urandom(16)).decode()
        transport.write(
            f"GET {self.path} HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: "
            f"Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode()
        )

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed.done():
            self.closed.set_result(None)

    def data_received(self, data: bytes) -> None:
        buf = self.buf
        buf += data
        if not self.upgraded:
            end = buf.find(b"\r\n\r\n")
            if end < 0:
                return
            assert buf.startswith(b"HTTP/1.1 101"), bytes(buf[:80])
            del buf[: end + 4]
            self.upgraded = True
        pos = 0
        while len(buf) - pos >= 2:
            n, head = buf[pos + 1] & 0x7F, 2
            if n == 126:
                if len(buf) - pos < 4:
                    break
                n, head = int.from_bytes(buf[pos + 2 : pos + 4], "big"), 4
            elif n == 127:
                if len(buf) - pos < 10:
                    break
                n, head = int.from_bytes(buf[pos + 2 : pos + 10], "big"), 10
            if len(buf) - pos < head + n:
                break
            opcode = buf[pos] & 0x0F
            payload = bytes(buf[pos + head : pos + head + n])
            pos += head + n
            if opcode == 1:
                self.message(payload)
            elif opcode == 9:  # ping: a pong, masked with a zero key
                self.transport.write(bytes([0x8A, 0x80 | len(payload)]) + b"\0\0\0\0" + payload)
            elif opcode == 8:
                self.transport.close()
        del buf[:pos]

    def message(self, payload: bytes) -> None:
        if self.last < 0:  # the snapshot
            self.last = 0
            return
        stats = self.stats
        seq = int(payload[7 : payload.index(b",", 7)])
        head = payload[:80]
        dropped = b'"dropped"' in head
        if seq != self.last + 1 or dropped:
            stats.lost += json.loads(payload)["count"] if dropped else seq - self.last - 1
            stats.clients_losing.add(self.i)
        self.last = seq
        if b'"reading"' in head:
            stats.received += 1
            if seq % 10 == 0:
                m = json.loads(payload)
                stats.latency.append(
                    time.time() - dt.datetime.fromisoformat(m["time_utc"]).timestamp()
                )


async def raw_reader(i: int, port: int, path: str, stats: Stats, stop: asyncio.Event) -> None:
    loop = asyncio.get_running_loop()
    transport, proto = await loop.create_connection(
        lambda: RawReader(i, path, stats), "127.0.0.1", port
    )
    try:
        await asyncio.wait(
            [asyncio.ensure_future(stop.wait()), proto.closed], return_when=asyncio.FIRST_COMPLETED
        )
    finally:
        transport.close()


def stuck_client(port: int, path: str) -> socket.socket:
    """A client that completes the handshake and then never reads."""
    sock = socket.create_connection(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(
        f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode()
    )
    assert sock.recv(12) == b"HTTP/1.1 101"
    return sock


async def run_clients(
    args: argparse.Namespace,
    url: str,
    port: int,
    path: str,
    n: int,
    stats: Stats,
    tasks: list,
    stop: asyncio.Event,
    first: int = 0,
) -> None:
    for i in range(first, first + n):
        tasks.append(
            asyncio.create_task(
                reader(i, url, stats, stop)
                if args.client == "websockets"
                else raw_reader(i, port, path, stats, stop)
            )
        )
        if i % 20 == 19:
            await asyncio.sleep(0.05)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clients", type=int, default=100)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=50.0, help="rate_hz each client asks for")
    ap.add_argument(
        "--ramp",
        action="store_true",
        help="add --step clients every --step-seconds until one loses",
    )
    ap.add_argument("--step", type=int, default=50)
    ap.add_argument("--step-seconds", type=float, default=10.0)
    ap.add_argument("--max-clients", type=int, default=1000)
    ap.add_argument(
        "--client",
        choices=("raw", "sweep", "websockets"),
        default="raw",
        help="the reading clients: raw frames read by a few bytes operations, plain sockets swept "
        "every 10 ms and counted in bulk, or the websockets library",
    )
    ap.add_argument(
        "--event-loop",
        choices=("asyncio", "uvloop"),
        help="the daemon's event loop (default: what `tiltlab serve` picks, uvloop when installed)",
    )
    ap.add_argument(
        "--ws",
        choices=("websockets", "websockets-sansio", "wsproto"),
        help="the daemon's WebSocket implementation (default: what `tiltlab serve` picks)",
    )
    args = ap.parse_args()

    work = Path(tempfile.mkdtemp(prefix="bench-ws-"))
    bench = start_simulated_bench(
        "seed000", "stage", Clock(1.0), directory=work / "ports", output_rate_hz=50
    )
    cfg = work / "bench.toml"
    write_text_atomic(cfg, bench.toml)
    port = free_port()
    env = {**os.environ, "TILTLAB_DATA_DIR": str(work / "data")}
    # the daemon as `tiltlab serve` runs it, but for the event loop or WebSocket implementation
    # asked for here (a comparison): uvicorn's Config is given them in the daemon's process before
    # the command runs
    given: dict[str, object] = {
        k: v for k, v in (("loop", args.event_loop), ("ws", args.ws)) if v is not None
    }
    if args.client == "sweep":
        # the swept clients count messages, they do not answer pings
        given["ws_ping_interval"] = None
    launch = (
        "import sys, uvicorn; init = uvicorn.Config.__init__; "
        f"uvicorn.Config.__init__ = lambda self, *a, **k: init(self, *a, **{{**k, **{given!r}}}); "
        "from service.cli import main; sys.exit(main(sys.argv[1:]))"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", launch, "serve", "--port", str(port), "--bench-config", str(cfg)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/health", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise SystemExit("the daemon did not start")
            time.sleep(0.2)
        token = (work / "data" / "admin.token").read_text().strip()
        path = f"/ws/readings?token={token}&rate_hz={args.rate:g}&history_s=1"
        url = f"ws://127.0.0.1:{port}{path}"
        # the clients in a process of their own: the simulated sensors keep their 50 Hz whatever the
        # clients cost
        run = (
            (lambda: sys.exit(sweep_run(args, port, path, proc.pid)))
            if args.client == "sweep"
            else (lambda: sys.exit(asyncio.run(bench_run(args, url, port, path, proc.pid))))
        )
        clients = multiprocessing.get_context("fork").Process(target=run)
        clients.start()
        clients.join()
        return clients.exitcode or 0
    finally:
        proc.terminate()
        proc.wait(20)
        bench.close()


async def bench_run(args: argparse.Namespace, url: str, port: int, path: str, pid: int) -> int:
    stats = Stats()
    stop = asyncio.Event()
    tasks: list = []
    stuck = stuck_client(port, path)
    try:
        if not args.ramp:
            await run_clients(args, url, port, path, args.clients, stats, tasks, stop)
            await asyncio.sleep(2.0)  # connected and past their snapshots
            stats.latency.clear()
            received0, lost0 = stats.received, stats.lost
            cpu0, t0 = cpu_s(pid), time.monotonic()
            await asyncio.sleep(args.seconds)
            cpu, wall = cpu_s(pid) - cpu0, time.monotonic() - t0
            report(
                f"{args.clients} clients at {args.rate:g} Hz + 1 never reading, {wall:.0f} s",
                stats,
                stats.received - received0,
                stats.lost - lost0,
                cpu,
                wall,
            )
        else:
            n = 0
            best = 0
            while n < args.max_clients:
                await run_clients(args, url, port, path, args.step, stats, tasks, stop, first=n)
                n += args.step
                await asyncio.sleep(2.0)
                stats.latency.clear()
                received0, lost0 = stats.received, stats.lost
                cpu0, t0 = cpu_s(pid), time.monotonic()
                await asyncio.sleep(args.step_seconds)
                cpu, wall = cpu_s(pid) - cpu0, time.monotonic() - t0
                lost = stats.lost - lost0
                rate = (stats.received - received0) / wall
                report(f"ramp: {n} clients", stats, stats.received - received0, lost, cpu, wall)
                if saturated(args, n, best, rate, lost or len(stats.clients_losing)):
                    break
                best = n
            else:
                print(f"ramp: kept up to {n} clients", flush=True)
    finally:
        stop.set()
        await asyncio.gather(*tasks, return_exceptions=True)
        stuck.close()
    return 0


class Swept:
    """One reading client as a plain non-blocking socket, read whole buffers at a time.

    Reading messages are `{"seq":N,...` (each client's seq in front of the shared body), so the
    client counts that marker in what arrived (bytes.count, in C) and reads the seq of the last one:
    with no loss, the seqs run on by exactly the number of messages. A `"dropped"` message (the
    daemon's notice that it dropped some for this client) or a gap counts as loss. One message in
    each sweep is parsed for its time (latency)."""

    MARK = b'{"seq":'
    # a marker split over two reads is counted once: the tail is kept and counted again, minus its
    # own
    CARRY = 15

    def __init__(self, port: int, path: str) -> None:
        sock = socket.create_connection(("127.0.0.1", port))
        key = base64.b64encode(os.urandom(16)).decode()
        sock.sendall(
            f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: "
            f"Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode()
        )
        head = b""
        while b"\r\n\r\n" not in head:
            got = sock.recv(4096)
            if not got:
                raise SystemExit("the daemon closed a stream during its handshake")
            head += got
        assert head.startswith(b"HTTP/1.1 101"), head[:80]
        sock.setblocking(False)
        self.sock = sock
        self.tail = b""
        self.first_seq: int | None = None
        self.last_seq = 0
        self.readings = 0
        self.dropped = 0
        self.closed = False
        self.take(head[head.index(b"\r\n\r\n") + 4 :])

    def sweep(self, latency: list[float]) -> None:
        while not self.closed:
            try:
                got = self.sock.recv(1 << 18)
            except BlockingIOError:
                return
            if not got:
                self.closed = True
                return
            self.take(got, latency)

    def take(self, got: bytes, latency: list[float] | None = None) -> None:
        data = self.tail + got
        tail = self.tail
        self.readings += data.count(self.MARK) - tail.count(self.MARK)
        self.dropped += data.count(b'"dropped"') - tail.count(b'"dropped"')
        self.tail = data[-self.CARRY :]
        at = data.rfind(self.MARK)
        while at >= 0 and data.find(b",", at + 7) < 0:  # the last marker whose seq arrived whole
            at = data.rfind(self.MARK, 0, at)
        if at < 0:
            return
        end = data.find(b",", at + 7)
        if self.first_seq is None:
            first = data.find(self.MARK)
            self.first_seq = int(data[first + 7 : data.find(b",", first + 7)])
        self.last_seq = max(self.last_seq, int(data[at + 7 : end]))
        if latency is not None:
            t = data.find(b'"time_utc": "', end)
            close = data.find(b'"', t + 13) if t > 0 else -1
            if close > 0:
                latency.append(
                    time.time()
                    - dt.datetime.fromisoformat(data[t + 13 : close].decode()).timestamp()
                )

    def lost(self) -> int:
        if self.first_seq is None:
            return 0
        return max(0, self.last_seq - self.first_seq + 1 - self.readings) + self.dropped


def sweep_run(args: argparse.Namespace, port: int, path: str, pid: int) -> int:
    """The ramp (or one run) with `Swept` clients, every socket read every 10 ms from one thread."""
    stats = Stats()
    clients: list[Swept] = []
    stuck = stuck_client(port, path)

    def sweep_for(seconds: float) -> None:
        end = time.monotonic() + seconds
        while (now := time.monotonic()) < end:
            for c in clients:
                c.sweep(stats.latency)
            time.sleep(max(0.0, 0.010 - (time.monotonic() - now)))

    def measure(what: str, seconds: float) -> tuple[int, float]:
        sweep_for(2.0)  # connected and past their snapshots
        stats.latency.clear()
        received0 = sum(c.readings for c in clients)
        lost0 = sum(c.lost() for c in clients)
        cpu0, own0, t0 = cpu_s(pid), time.process_time(), time.monotonic()
        sweep_for(seconds)
        cpu, own, wall = cpu_s(pid) - cpu0, time.process_time() - own0, time.monotonic() - t0
        received = sum(c.readings for c in clients) - received0
        lost = sum(c.lost() for c in clients) - lost0 + sum(c.closed for c in clients)
        report(what, stats, received, lost, cpu, wall)
        print(f"  the swept clients: {100 * own / wall:.0f} % of a core", flush=True)
        return lost, received / wall

    def connect(n: int) -> None:
        for i in range(n):
            clients.append(Swept(port, path))
            if i % 20 == 19:
                sweep_for(0.05)

    try:
        if not args.ramp:
            connect(args.clients)
            measure(
                f"{args.clients} swept clients at {args.rate:g} Hz + 1 never reading, "
                f"{args.seconds:.0f} s",
                args.seconds,
            )
            return 0
        best = 0
        while len(clients) < args.max_clients:
            connect(args.step)
            n = len(clients)
            lost, rate = measure(f"ramp: {n} clients", args.step_seconds)
            if saturated(args, n, best, rate, lost):
                break
            best = n
        else:
            print(f"ramp: kept up to {len(clients)} clients", flush=True)
    finally:
        for c in clients:
            c.sock.close()
        stuck.close()
    return 0


def saturated(args: argparse.Namespace, n: int, best: int, rate: float, lost: int) -> bool:
    """The ramp's stopping rule: a reading client lost a message, or they got under 95 % of what
    they asked."""
    if not lost and rate >= 0.95 * n * args.rate:
        return False
    why = "lost messages" if lost else "waited"
    print(
        f"ramp: the reading clients first {why} with {n} clients ({rate:.0f} messages/s); "
        f"{best} clients kept up ({best * args.rate:.0f} messages/s)",
        flush=True,
    )
    return True


def report(what: str, stats: Stats, received: int, lost: int, cpu: float, wall: float) -> None:
    lat = np.array(stats.latency) * 1000.0
    p50, p99 = (np.percentile(lat, 50), np.percentile(lat, 99)) if lat.size else (float("nan"),) * 2
    per_msg = 1e6 * cpu / received if received else float("nan")
    print(
        f"{what}: received {received} ({received / wall:.0f}/s), lost {lost}, latency p50 "
        f"{p50:.1f} ms p99 {p99:.1f} ms, daemon CPU {cpu:.1f} s in {wall:.0f} s "
        f"({100 * cpu / wall:.0f} % of a core, {per_msg:.0f} us a message)",
        flush=True,
    )


if __name__ == "__main__":
    raise SystemExit(main())
