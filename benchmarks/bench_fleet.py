"""The fleet on one machine: readings of 4 benches through one NATS server to a dashboard on another
node, and the cost of a command carried to a bench's owner.

Starts a NATS server (JetStream) of its own, a fresh PostgreSQL schema, four bench daemons (each a
node with one simulated stage bench, publishing to the fleet at 25 Hz) and a fifth daemon, the
"dashboard node", then for `--seconds`:
* one WebSocket client per bench on the dashboard node (`/ws/readings?bench=bench-k&rate_hz=25`):
  messages received, lost (gaps in `seq`, `dropped` counts), and end-to-end latency (the reading's
  `time_utc` on its bench's node to its receipt here; one machine, one clock);
* `POST /stage/stop` for bench-1 asked `--commands` times of its own node and as many times of the
  dashboard node (carried to bench-1's node by request/reply): round-trip p50/p99 of each.

    .venv/bin/python benchmarks/bench_fleet.py                # 30 s, 200 stops each way
    .venv/bin/python benchmarks/bench_fleet.py --seconds 10 --commands 50
"""

from __future__ import annotations

import argparse
import asyncio
import datetime as dt
import json
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path

import httpx
import numpy as np
from websockets.asyncio.client import connect

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tests.helpers.fleet import Daemon, NatsServer, eventually, postgres_schema_url  # noqa: E402
from tests.helpers.running_service import free_port  # noqa: E402

BENCHES = 4
RATE_HZ = 25.0


async def watch(url: str, token: str, bench: str, seconds: float) -> dict:
    latencies: list[float] = []
    lost = received = 0
    last_seq = 0
    async with connect(
        f"{url.replace('http', 'ws')}/ws/readings?bench={bench}&rate_hz={RATE_HZ:g}&token={token}",
        max_size=2**22,
    ) as ws:
        json.loads(await ws.recv())  # the snapshot
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                msg = json.loads(
                    await asyncio.wait_for(ws.recv(), timeout=max(0.05, end - time.monotonic()))
                )
            except TimeoutError:
                break
            now = dt.datetime.now(dt.UTC)
            lost += msg["seq"] - last_seq - 1
            last_seq = msg["seq"]
            if msg["type"] == "dropped":
                continue
            received += 1
            latencies.append((now - dt.datetime.fromisoformat(msg["time_utc"])).total_seconds())
    return {"bench": bench, "received": received, "lost": lost, "latencies": latencies}


def stops(url: str, auth: dict, bench: str, n: int) -> list[float]:
    times = []
    with httpx.Client(timeout=30) as client:
        for _ in range(n):
            start = time.perf_counter()
            answer = client.post(f"{url}/stage/stop", headers=auth, json={"bench": bench})
            times.append(time.perf_counter() - start)
            assert answer.status_code == 200, answer.text
    return times


def ms(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q) * 1e3)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--commands", type=int, default=200)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack, postgres_schema_url() as db:
        root = Path(tmp)
        nats = NatsServer(root / "nats", free_port())
        nats.start()
        stack.callback(nats.stop)
        common = {
            "TILTLAB_DATABASE_URL": db,
            "TILTLAB_BROKER_URL": nats.url,
            "TILTLAB_FLEET_RATE_HZ": f"{RATE_HZ:g}",
        }
        nodes = [
            stack.enter_context(
                Daemon(
                    root / f"node-{k}",
                    {**common, "TILTLAB_NODE": f"node-{k}", "TILTLAB_SIM_BENCH_NAME": f"bench-{k}"},
                )
            )
            for k in range(1, BENCHES + 1)
        ]
        token = (root / "node-1" / "admin.token").read_text().strip()
        auth = {"Authorization": f"Bearer {token}"}
        dash = stack.enter_context(
            Daemon(
                root / "dashboard",
                {
                    **common,
                    "TILTLAB_NODE": "dashboard",
                    "TILTLAB_SIM_BENCH_NAME": "bench-dashboard",
                },
            )
        )
        names = [f"bench-{k}" for k in range(1, BENCHES + 1)]
        eventually(
            lambda: httpx.get(f"{dash.url}/benches", headers=auth).json()["benches"],
            lambda bs: all(any(b["name"] == n and b["online"] for b in bs) for n in names),
            timeout_s=60,
        )

        async def all_watch() -> list[dict]:
            return await asyncio.gather(*(watch(dash.url, token, n, args.seconds) for n in names))

        results = asyncio.run(all_watch())
        latencies = [x for r in results for x in r["latencies"]]
        print(
            f"readings: {BENCHES} benches published at {RATE_HZ:g} Hz, watched {args.seconds:g} s "
            "on another node"
        )
        for r in results:
            print(
                f"  {r['bench']}: {r['received']} received ({r['received'] / args.seconds:.1f}/s), "
                f"{r['lost']} lost"
            )
        print(
            f"  end-to-end latency (reading time -> dashboard client): p50 {ms(latencies, 50):.1f} "
            "ms,"
            f" p99 {ms(latencies, 99):.1f} ms, lost {sum(r['lost'] for r in results)}"
        )

        local = stops(nodes[0].url, auth, "bench-1", args.commands)
        remote = stops(dash.url, auth, "bench-1", args.commands)
        print(f"POST /stage/stop for bench-1, {args.commands} each:")
        print(
            f"  asked of its own node:       p50 {ms(local, 50):.2f} ms, p99 {ms(local, 99):.2f} ms"
        )
        print(
            f"  asked of another node:       p50 {ms(remote, 50):.2f} ms, p99 "
            f"{ms(remote, 99):.2f} ms"
        )
        print(f"  carried to the owner adds:   p50 {ms(remote, 50) - ms(local, 50):.2f} ms")


if __name__ == "__main__":
    main()
