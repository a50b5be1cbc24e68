"""GET /tilt and the reading stream while a diagnosis runs, against the same daemon with none
running.

Starts `tiltlab serve` (simulated stage bench, real drivers, sped up) on a fresh data directory,
calibrates a 7 x 7 grid (kinematic), then measures twice for `--duration` seconds each: first with
nothing else running, then while diagnoses of that record run back to back (`POST
/records/{id}/diagnose`, the discrepancy workflow in the daemon's worker process). Each window sends
/tilt and /health on an open-loop schedule (`--rate` requests/s, half each; latency from the
scheduled send time) and keeps one WebSocket reading client open (latency from a reading's time_utc
to its receipt, one machine clock; seq gaps counted).

    python benchmarks/bench_diagnosis_latency.py                 # 30 s per window at 200 req/s
    python benchmarks/bench_diagnosis_latency.py --duration 10
"""

from __future__ import annotations

import argparse
import asyncio
import datetime as dt
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
from websockets.asyncio.client import connect

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench_tilt_latency import free_port, run_rate  # noqa: E402


async def watch(port: int, token: str, seconds: float) -> dict:
    lat: list[float] = []
    gaps = last = 0
    async with connect(f"ws://127.0.0.1:{port}/ws/readings?rate_hz=25&token={token}") as ws:
        json.loads(await ws.recv())
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                msg = json.loads(
                    await asyncio.wait_for(ws.recv(), timeout=max(0.05, end - time.monotonic()))
                )
            except TimeoutError:
                break
            gaps += msg["seq"] - last - 1
            last = msg["seq"]
            if msg["type"] == "reading":
                lat.append(
                    (
                        dt.datetime.now(dt.UTC) - dt.datetime.fromisoformat(msg["time_utc"])
                    ).total_seconds()
                )
    a = np.asarray(lat) * 1e3
    return {
        "n": len(lat),
        "gaps": gaps,
        "p50_ms": float(np.percentile(a, 50)),
        "p99_ms": float(np.percentile(a, 99)),
    }


async def window(port: int, token: str, rate: float, seconds: float) -> tuple[dict, dict]:
    http, stream = await asyncio.gather(
        run_rate(port, token, rate, seconds, 20), watch(port, token, seconds)
    )
    return http, stream


def line(name: str, http: dict, stream: dict) -> str:
    t, h = http["/tilt"], http["/health"]
    return (
        f"{name:>22}: /tilt p50 {t['p50_ms']:.2f} ms p99 {t['p99_ms']:.2f} ms (errors "
        f"{t['errors']}); /health p50 {h['p50_ms']:.2f} p99 {h['p99_ms']:.2f} ms; stream p50 "
        f"{stream['p50_ms']:.1f} ms p99 {stream['p99_ms']:.1f} ms ({stream['n']} readings, "
        f"{stream['gaps']} lost)"
    )


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
        async with httpx.AsyncClient(base_url=base, timeout=60) as client:
            for _ in range(300):
                try:
                    await client.get("/health")
                    break
                except httpx.TransportError:
                    await asyncio.sleep(0.2)
            h = {"Authorization": "Bearer " + (data / "admin.token").read_text().strip()}
            token = h["Authorization"].split()[1]
            job = (
                await client.post(
                    "/calibrations",
                    headers=h,
                    json={
                        "procedure": "stage-grid",
                        "method": "kinematic",
                        "samples_per_point": 10,
                        "grid": {"x_deg": [-4, 4], "y_deg": [-4, 4], "n_x": 7, "n_y": 7},
                        "settle": {"tolerance_deg": 0.002, "window_s": 2.0, "timeout_s": 600},
                    },
                )
            ).json()
            while job["state"] not in ("succeeded", "failed", "cancelled"):
                await asyncio.sleep(1)
                job = (await client.get(f"/calibrations/{job['id']}", headers=h)).json()
            assert job["state"] == "succeeded", job
            record = job["record"]["id"]
            print(
                f"record {record} from a 7 x 7 grid; {args.duration:g} s per window at "
                f"{args.rate:g} req/s"
            )
            quiet = await window(port, token, args.rate, args.duration)
            print(line("no diagnosis", *quiet))

            done = 0
            stop = asyncio.Event()

            async def diagnose() -> None:
                nonlocal done
                while not stop.is_set():
                    d = (
                        await client.post(f"/records/{record}/diagnose", headers=h, json={})
                    ).json()
                    while d["state"] in ("queued", "running"):
                        await asyncio.sleep(0.5)
                        d = (await client.get(f"/diagnoses/{d['id']}", headers=h)).json()
                    done += 1

            runner = asyncio.create_task(diagnose())
            await asyncio.sleep(1.0)  # the first diagnosis is under way
            busy = await window(port, token, args.rate, args.duration)
            stop.set()
            await runner
            print(line("diagnoses running", *busy) + f"; {done} diagnoses finished meanwhile")
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=30.0)
    p.add_argument("--rate", type=float, default=200.0)
    p.add_argument("--sim-speed", type=float, default=5.0)
    asyncio.run(main_async(p.parse_args()))


if __name__ == "__main__":
    main()
