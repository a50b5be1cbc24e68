"""Two daemons, one lab: a NATS server of the test's own, one PostgreSQL database, two simulated
benches.

Each daemon lists both benches with their nodes; jobs on both benches are started through one
node and both succeed; records are read through either node; the other node's readings stream
through this one; `db verify` passes afterwards; a third daemon claiming an owned bench exits 2;
stopping the broker leaves each node serving its own bench, and restarting it brings the other
node's bench back without restarting a daemon.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from websockets.sync.client import connect as ws_connect

from tests.helpers.fleet import UNREACHABLE, Daemon, NatsServer
from tests.helpers.running_service import free_port
from tests.helpers.waiting import eventually

pytestmark = [pytest.mark.postgres, pytest.mark.slow]

GRID = {"x_deg": [-2.0, 2.0], "y_deg": [-2.0, 2.0], "n_x": 3, "n_y": 3}
# 2-s windows: two simulated benches at 20x share the machine with the test, and readings may lag
SETTLE = {"tolerance_deg": 0.002, "window_s": 2.0, "timeout_s": 600.0}


@pytest.fixture
def nats_server(tmp_path: Path):
    server = NatsServer(tmp_path / "nats", free_port())
    server.start()
    yield server
    server.stop()


def test_two_daemons_serve_one_fleet(
    tmp_path: Path, nats_server: NatsServer, database_url: str
) -> None:
    common = {
        "TILTLAB_DATABASE_URL": database_url,
        "TILTLAB_BROKER_URL": nats_server.url,
        "TILTLAB_SIM_SPEED": "20",
        "TILTLAB_FLEET_LEASE_S": "3",
    }
    with Daemon(
        tmp_path / "a", {**common, "TILTLAB_NODE": "node-a", "TILTLAB_SIM_BENCH_NAME": "bench-a"}
    ) as a:
        # the first node made the lab's admin token
        token = (tmp_path / "a" / "admin.token").read_text().strip()
        auth = {"Authorization": f"Bearer {token}"}
        with Daemon(
            tmp_path / "b",
            {**common, "TILTLAB_NODE": "node-b", "TILTLAB_SIM_BENCH_NAME": "bench-b"},
        ) as b:
            # every node lists every bench with its node
            for node in (a, b):
                listing = eventually(
                    lambda node=node: _fleet_view(node.url, auth),
                    until=lambda v: (
                        v.get("bench-a", {}).get("online") and v.get("bench-b", {}).get("online")
                    ),
                    timeout_s=30,
                    every_s=0.2,
                    ignoring=UNREACHABLE,
                    what="both benches online",
                )
                assert (
                    listing["bench-a"]["node"] == "node-a"
                    and listing["bench-b"]["node"] == "node-b"
                )

            # a job on each bench, both started through node a
            jobs = {}
            for bench in ("bench-a", "bench-b"):
                answer = httpx.post(
                    f"{a.url}/calibrations",
                    headers=auth,
                    timeout=30,
                    json={
                        "bench": bench,
                        "procedure": "stage-grid",
                        "method": "kinematic",
                        "grid": GRID,
                        "samples_per_point": 8,
                        "validation": {"n_points": 2},
                        "settle": SETTLE,
                    },
                )
                assert answer.status_code == 202, answer.text
                jobs[bench] = answer.json()["id"]
            for bench, job_id in jobs.items():
                job = eventually(
                    lambda job_id=job_id: httpx.get(
                        f"{a.url}/calibrations/{job_id}", headers=auth
                    ).json(),
                    until=lambda j: j["state"] in ("succeeded", "failed", "cancelled"),
                    timeout_s=300,
                    every_s=0.2,
                    ignoring=UNREACHABLE,
                    what="the job ended",
                )
                assert job["state"] == "succeeded", (job["error"], job)
                assert job["bench"] == bench
                for node in (a, b):  # the jobs of either bench, listed through either node
                    listed = httpx.get(
                        f"{node.url}/calibrations", headers=auth, params={"bench": bench}
                    ).json()
                    assert [j["id"] for j in listed["jobs"]] == [job_id]
                record_id = job["record"]["id"]
                for node in (a, b):  # the records of both benches, read through either node
                    record = httpx.get(f"{node.url}/records/{record_id}", headers=auth)
                    assert record.status_code == 200, record.text
                    assert record.json()["bench"] == bench
                    listed = httpx.get(
                        f"{node.url}/records", headers=auth, params={"bench": bench}
                    ).json()["records"]
                    assert [r["id"] for r in listed] == [record_id]

            # node b's bench through node a: /tilt (with the node it came from) and its live
            # readings
            tilt = httpx.get(f"{a.url}/tilt", headers=auth, params={"bench": "bench-b"})
            assert tilt.status_code == 200, tilt.text
            assert tilt.json()["node"] == "node-b" and tilt.json()["age_s"] is not None
            with ws_connect(
                f"{a.url.replace('http', 'ws')}/ws/readings?bench=bench-b&token={token}"
            ) as ws:
                snapshot = json.loads(ws.recv(timeout=10))
                assert snapshot["type"] == "snapshot" and snapshot["bench"] == "bench-b"
                readings = [json.loads(ws.recv(timeout=10)) for _ in range(5)]
            assert all(r["type"] == "reading" for r in readings)
            assert [r["seq"] for r in readings] == list(range(1, 6))

            # a third daemon claiming node a's bench refuses to start, naming bench and node
            third = subprocess.run(
                [sys.executable, "-m", "service", "serve", "--port", str(free_port())],
                env={
                    **os.environ,
                    **common,
                    "TILTLAB_DATA_DIR": str(tmp_path / "c"),
                    "TILTLAB_NODE": "node-c",
                    "TILTLAB_SIM_BENCH_NAME": "bench-a",
                },
                capture_output=True,
                text=True,
                timeout=120,
            )
            assert third.returncode == 2, third.stderr
            assert "bench-a" in third.stderr and "node-a" in third.stderr

            # the broker goes away: each node serves its own bench; a command for the other's is a
            # 503
            nats_server.stop()
            assert (
                httpx.get(f"{a.url}/tilt", headers=auth, params={"bench": "bench-a"}).status_code
                == 200
            )
            gone = eventually(
                lambda: httpx.get(f"{a.url}/tilt", headers=auth, params={"bench": "bench-b"}),
                until=lambda r: r.status_code == 503,
                timeout_s=30,
                every_s=0.2,
                ignoring=UNREACHABLE,
                what="bench-b gone (503)",
            )
            assert "node-b" in gone.json()["detail"]

            # the broker comes back: node b's bench returns through node a without a restart
            nats_server.start()
            back = eventually(
                lambda: httpx.get(f"{a.url}/tilt", headers=auth, params={"bench": "bench-b"}),
                until=lambda r: r.status_code == 200,
                timeout_s=60,
                every_s=0.2,
                ignoring=UNREACHABLE,
                what="bench-b back (200)",
            )
            assert back.json()["node"] == "node-b"

        # node b stopped: its bench is listed as offline by node a
        listing = eventually(
            lambda: _fleet_view(a.url, auth),
            until=lambda v: not v["bench-b"]["online"],
            timeout_s=30,
            every_s=0.2,
            ignoring=UNREACHABLE,
            what="bench-b offline",
        )
        assert listing["bench-b"]["state"] == "offline"

    verify = subprocess.run(
        [sys.executable, "-m", "service", "db", "verify"],
        capture_output=True,
        text=True,
        env={
            **os.environ,
            "TILTLAB_DATABASE_URL": database_url,
            "TILTLAB_DATA_DIR": str(tmp_path / "a"),
        },
        timeout=120,
    )
    assert verify.returncode == 0, verify.stdout + verify.stderr


def _fleet_view(url: str, auth: dict[str, str]) -> dict[str, dict]:
    benches = httpx.get(f"{url}/benches", headers=auth, timeout=10).json()["benches"]
    return {b["name"]: b for b in benches}
