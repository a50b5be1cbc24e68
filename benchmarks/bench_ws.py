"""Reading stream under load: N WebSocket clients at 50 Hz on one bench, plus one client that never reads.

Starts a simulated stage bench whose sensors output 50 Hz (pseudo-terminals, in this process) and
`tiltlab serve --bench-config` on it in a subprocess, then connects the clients and reports messages
lost by the reading clients (seq gaps; target 0), delivery latency p50/p99 (message time_utc to
receipt, same machine clock), and the daemon's CPU time from /proc/<pid>/stat.

    .venv/bin/python benchmarks/bench_ws.py                 # 100 clients, 60 s
    .venv/bin/python benchmarks/bench_ws.py --seconds 10
    .venv/bin/python benchmarks/bench_ws.py --ramp          # add clients until one first loses a message
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import datetime as dt
import json
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
from tests.api.running_service import free_port  # noqa: E402

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


def stuck_client(port: int, path: str) -> socket.socket:
    """A client that completes the handshake and then never reads."""
    sock = socket.create_connection(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                 f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
    assert sock.recv(12) == b"HTTP/1.1 101"
    return sock


async def run_clients(url: str, n: int, seconds: float, pid: int, stats: Stats, tasks: list, stop: asyncio.Event,
                      first: int = 0) -> None:
    for i in range(first, first + n):
        tasks.append(asyncio.create_task(reader(i, url, stats, stop)))
        if i % 20 == 19:
            await asyncio.sleep(0.05)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clients", type=int, default=100)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=50.0, help="rate_hz each client asks for")
    ap.add_argument("--ramp", action="store_true", help="add --step clients every --step-seconds until one loses")
    ap.add_argument("--step", type=int, default=50)
    ap.add_argument("--step-seconds", type=float, default=10.0)
    ap.add_argument("--max-clients", type=int, default=1000)
    args = ap.parse_args()

    work = Path(tempfile.mkdtemp(prefix="bench-ws-"))
    bench = start_simulated_bench("seed000", "stage", Clock(1.0), directory=work / "ports", output_rate_hz=50)
    cfg = work / "bench.toml"
    write_text_atomic(cfg, bench.toml)
    port = free_port()
    env = {**os.environ, "TILTLAB_DATA_DIR": str(work / "data")}
    proc = subprocess.Popen([sys.executable, "-m", "service", "serve", "--port", str(port), "--bench-config", str(cfg)],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
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
        return asyncio.run(bench_run(args, url, port, path, proc.pid))
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
            await run_clients(url, args.clients, args.seconds, pid, stats, tasks, stop)
            await asyncio.sleep(2.0)  # connected and past their snapshots
            stats.latency.clear()
            received0, lost0 = stats.received, stats.lost
            cpu0, t0 = cpu_s(pid), time.monotonic()
            await asyncio.sleep(args.seconds)
            cpu, wall = cpu_s(pid) - cpu0, time.monotonic() - t0
            report(f"{args.clients} clients at {args.rate:g} Hz + 1 never reading, {wall:.0f} s", stats,
                   stats.received - received0, stats.lost - lost0, cpu, wall)
        else:
            n = 0
            best = 0
            while n < args.max_clients:
                await run_clients(url, args.step, args.step_seconds, pid, stats, tasks, stop, first=n)
                n += args.step
                await asyncio.sleep(2.0)
                stats.latency.clear()
                received0, lost0 = stats.received, stats.lost
                cpu0, t0 = cpu_s(pid), time.monotonic()
                await asyncio.sleep(args.step_seconds)
                cpu, wall = cpu_s(pid) - cpu0, time.monotonic() - t0
                lost = stats.lost - lost0
                report(f"ramp: {n} clients", stats, stats.received - received0, lost, cpu, wall)
                if lost or stats.clients_losing:
                    print(f"ramp: first loss with {n} reading clients; {best} kept up", flush=True)
                    break
                best = n
            else:
                print(f"ramp: no loss up to {n} clients", flush=True)
    finally:
        stop.set()
        await asyncio.gather(*tasks, return_exceptions=True)
        stuck.close()
    return 0


def report(what: str, stats: Stats, received: int, lost: int, cpu: float, wall: float) -> None:
    lat = np.array(stats.latency) * 1000.0
    p50, p99 = (np.percentile(lat, 50), np.percentile(lat, 99)) if lat.size else (float("nan"),) * 2
    print(f"{what}: received {received} ({received / wall:.0f}/s), lost {lost}, latency p50 {p50:.1f} ms "
          f"p99 {p99:.1f} ms, daemon CPU {cpu:.1f} s in {wall:.0f} s ({100 * cpu / wall:.0f} % of a core)",
          flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
