"""GET /tilt throughput beside a one-route FastAPI app served by the same uvicorn, back to back,
with wrk.

    python benchmarks/bench_tilt_throughput.py                 # 3 rounds of wrk -t2 -c32 -d15s each
    python benchmarks/bench_tilt_throughput.py --rounds 1 --seconds 5

Starts `tiltlab serve` (simulated stage bench, --sim-speed 20) on a fresh data directory, calibrates
the bench (a 3 x 3 kinematic stage grid) and activates the record, so `/tilt` serves a corrected
tilt with its uncertainty, as a client of a calibrated bench sees it. Beside it, a FastAPI app with
one route answering a small JSON object, served by uvicorn with the same settings as the daemon's
(log level info: an access log line per request; the event loop and HTTP parser uvicorn finds
installed) in the same environment: the ceiling of the stack on this machine. Each round runs wrk on
the app, then on /tilt (with the admin token), and prints requests/s, the ratio and the non-2xx
answers; the load average is printed beside them. Needs `wrk` on the PATH.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

ONE_ROUTE_APP = """
import sys
import uvicorn
from fastapi import FastAPI

app = FastAPI()


@app.get("/tilt")
async def tilt() -> dict:
    return {"bench": "sim-stage", "table_tilt": {"x_deg": 0.1, "y_deg": -0.2}, "stale": False}


# as `tiltlab serve`: access log on
uvicorn.run(app, host="127.0.0.1", port=int(sys.argv[1]), log_level="info")
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_http(url: str, proc: subprocess.Popen[bytes], timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            httpx.get(url, timeout=2)
            return
        except httpx.TransportError:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"{url} did not come up") from None
            time.sleep(0.2)


def wrk(url: str, seconds: float, token: str | None) -> tuple[float, int, int]:
    """requests/s, requests, non-2xx answers (wrk -t2 -c32)."""
    cmd = ["wrk", "-t2", "-c32", f"-d{seconds:g}s", url]
    if token:
        cmd[1:1] = ["-H", f"Authorization: Bearer {token}"]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    rate = float(re.search(r"Requests/sec:\s+([\d.]+)", out).group(1))  # type: ignore[union-attr]
    total = int(re.search(r"(\d+) requests in", out).group(1))  # type: ignore[union-attr]
    bad = re.search(r"Non-2xx or 3xx responses: (\d+)", out)
    errors = re.search(r"Socket errors: .*", out)
    if errors:
        print(f"    wrk: {errors.group(0)}")
    return rate, total, int(bad.group(1)) if bad else 0


def calibrate(base: str, token: str) -> int:
    h = {"Authorization": f"Bearer {token}"}
    job = httpx.post(
        f"{base}/calibrations",
        headers=h,
        timeout=30,
        json={
            "procedure": "stage-grid",
            "method": "kinematic",
            "samples_per_point": 8,
            "grid": {"x_deg": [-2.0, 2.0], "y_deg": [-2.0, 2.0], "n_x": 3, "n_y": 3},
        },
    ).json()
    deadline = time.monotonic() + 300
    while True:
        state = httpx.get(f"{base}/calibrations/{job['id']}", headers=h, timeout=30).json()
        if state["state"] in ("succeeded", "failed", "cancelled"):
            break
        if time.monotonic() > deadline:
            raise SystemExit(f"the calibration did not end: {state}")
        time.sleep(0.5)
    if state["state"] != "succeeded":
        raise SystemExit(f"the calibration did not succeed: {state}")
    record = int(state["record"]["id"])
    httpx.post(f"{base}/records/{record}/activate", headers=h, timeout=30).raise_for_status()
    return record


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--sim-speed", type=float, default=20.0)
    args = ap.parse_args()
    if shutil.which("wrk") is None:
        raise SystemExit("wrk is not on the PATH (apt-get install wrk)")
    data = Path(tempfile.mkdtemp(prefix="tiltlab-bench-"))
    port, app_port = free_port(), free_port()
    env = {**os.environ, "TILTLAB_DATA_DIR": str(data)}
    daemon = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service",
            "serve",
            "--port",
            str(port),
            "--sim-speed",
            f"{args.sim_speed:g}",
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    app = subprocess.Popen(
        [sys.executable, "-c", ONE_ROUTE_APP, str(app_port)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    base, app_url = f"http://127.0.0.1:{port}", f"http://127.0.0.1:{app_port}/tilt"
    try:
        wait_http(f"{base}/health", daemon)
        wait_http(app_url, app)
        token = (data / "admin.token").read_text().strip()
        record = calibrate(base, token)
        body = httpx.get(
            f"{base}/tilt", headers={"Authorization": f"Bearer {token}"}, timeout=30
        ).json()
        print(f"record {record} active; /tilt serves table_tilt {body['table_tilt']}")
        ratios = []
        for k in range(1, args.rounds + 1):
            load = os.getloadavg()[0]
            app_rate, app_n, app_bad = wrk(app_url, args.seconds, None)
            tilt_rate, tilt_n, tilt_bad = wrk(f"{base}/tilt", args.seconds, token)
            ratios.append(tilt_rate / app_rate)
            print(
                f"round {k} (load average {load:.2f}, {os.cpu_count()} cores): one-route app "
                f"{app_rate:,.0f} req/s ({app_bad} non-2xx of {app_n}); /tilt {tilt_rate:,.0f} "
                f"req/s ({tilt_bad} non-2xx of {tilt_n}); ratio {tilt_rate / app_rate:.2f}"
            )
        print(
            f"ratio /tilt / one-route app: median {sorted(ratios)[len(ratios) // 2]:.2f}"
            f" (min {min(ratios):.2f}, max {max(ratios):.2f})"
        )
    finally:
        for p in (app, daemon):
            p.terminate()
            p.wait(30)
        shutil.rmtree(data, ignore_errors=True)


if __name__ == "__main__":
    main()
