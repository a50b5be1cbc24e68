"""GET /tilt latency beside GET /health, at fixed request rates, while a calibration job runs.

Starts `tiltlab serve` (simulated stage bench on pseudo-terminals, real drivers, sped up) on a
fresh data directory, starts a stage-grid job on the same bench, and sends requests on an open
loop schedule (one request every 1/rate seconds, alternating /tilt and /health, each rate
shared between the two routes) from one local client (raw keep-alive connections) for `--duration`
seconds per rate. Latency is measured from the scheduled send time, so a slow server cannot hide
queueing.

    python benchmarks/bench_tilt_latency.py                   # 200 and 1000 req/s, 30 s each
    python benchmarks/bench_tilt_latency.py --duration 5      # a quick look
"""

from __future__ import annotations

import argparse
import asyncio
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Connection:
    """One keep-alive HTTP/1.1 connection on raw asyncio streams: far less client CPU per request
    than a full HTTP client library, so the figures are the server's and not the client's."""

    def __init__(self, port: int, token: str) -> None:
        self.port, self.token = port, token

    async def open(self) -> None:
        self.reader, self.writer = await asyncio.open_connection("127.0.0.1", self.port)

    async def get(self, path: str) -> int:
        self.writer.write(
            f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer "
            f"{self.token}\r\n\r\n".encode()
        )
        head = await self.reader.readuntil(b"\r\n\r\n")
        status = int(head.split(b" ", 2)[1])
        length = next(
            int(line.split(b":")[1])
            for line in head.split(b"\r\n")
            if line.lower().startswith(b"content-length")
        )
        await self.reader.readexactly(length)
        return status


async def run_rate(port: int, token: str, rate: float, duration_s: float, connections: int) -> dict:
    """Open loop: request i is due at t0 + i/rate on connection i mod `connections`; its latency
    counts from when it was due, so a server that falls behind shows it (no coordinated
    omission)."""
    lat: dict[str, list[float]] = {"/tilt": [], "/health": []}
    errors = {"/tilt": 0, "/health": 0}
    n = int(rate * duration_s)
    conns = [Connection(port, token) for _ in range(connections)]
    await asyncio.gather(*(c.open() for c in conns))
    t0 = time.perf_counter() + 0.2

    async def worker(k: int) -> None:
        c = conns[k]
        for i in range(k, n, connections):
            path = "/tilt" if i % 2 == 0 else "/health"
            due = t0 + i / rate
            delay = due - time.perf_counter()
            if delay > 0:
                await asyncio.sleep(delay)
            status = await c.get(path)
            if status == 200:
                lat[path].append(time.perf_counter() - due)
            else:
                errors[path] += 1

    await asyncio.gather(*(worker(k) for k in range(connections)))
    for c in conns:
        c.writer.close()
    out = {}
    for path, v in lat.items():
        a = np.array(v) * 1000
        out[path] = {
            "n": len(v),
            "errors": errors[path],
            "p50_ms": float(np.percentile(a, 50)),
            "p99_ms": float(np.percentile(a, 99)),
        }
    return out


async def main_async(args: argparse.Namespace) -> None:
    data = Path(tempfile.mkdtemp(prefix="tiltlab-bench-"))
    port = free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service",
            "serve",
            "--port",
            str(port),
            "--sim-speed",
            str(args.sim_speed),
        ],
        env={**os.environ, "TILTLAB_DATA_DIR": str(data)},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    base = f"http://127.0.0.1:{port}"
    try:
        limits = httpx.Limits(max_connections=200, max_keepalive_connections=200)
        async with httpx.AsyncClient(base_url=base, timeout=30, limits=limits) as client:
            for _ in range(300):
                try:
                    await client.get("/health")
                    break
                except httpx.TransportError:
                    await asyncio.sleep(0.2)
            h = {"Authorization": "Bearer " + (data / "admin.token").read_text().strip()}
            job = (
                await client.post(
                    "/calibrations",
                    headers=h,
                    json={
                        "procedure": "stage-grid",
                        "method": "kinematic",
                        "samples_per_point": 20,
                        "grid": {"x_deg": [-5, 5], "y_deg": [-5, 5], "n_x": 15, "n_y": 15},
                    },
                )
            ).json()
            print(
                f"job {job['id']} running on {job['bench']} (simulated bench {args.sim_speed:g}x); "
                f"{args.duration:g} s per rate, one local client, open loop"
            )
            token = h["Authorization"].split()[1]
            for rate in args.rates:
                res = await run_rate(port, token, rate, args.duration, args.connections)
                state = (await client.get(f"/calibrations/{job['id']}", headers=h)).json()
                print(
                    f"{rate:6.0f} req/s (half each): "
                    + "; ".join(
                        f"{p} p50 {v['p50_ms']:.2f} ms p99 {v['p99_ms']:.2f} ms (n {v['n']}, "
                        f"errors {v['errors']})"
                        for p, v in res.items()
                    )
                    + "; ratio p50 tilt/health "
                    f"{res['/tilt']['p50_ms'] / res['/health']['p50_ms']:.2f};"
                    f" job {state['state']} "
                    f"{state['progress']['points_done']}/{state['progress']['points_total']}"
                )
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rates", type=float, nargs="+", default=[200.0, 1000.0])
    p.add_argument("--duration", type=float, default=30.0)
    p.add_argument("--sim-speed", type=float, default=5.0)
    p.add_argument(
        "--connections", type=int, default=50, help="keep-alive connections of the client"
    )
    asyncio.run(main_async(p.parse_args()))


if __name__ == "__main__":
    main()
