"""PostgreSQL going away while the daemon runs, through a proxy the test cuts and restores.

The sample writer keeps what it was handed through an outage and stores each sample once when the
database returns, even when the answer to a COMMIT was lost; a job's point written twice is
stored once. A daemon keeps serving /tilt through a 10-s outage, /health says the database is
away and which job waits; the job goes on when the database returns and succeeds with every
sample stored once; an outage longer than TILTLAB_DB_OUTAGE_S fails the job naming it
(database_unreachable), and a user's write meanwhile is a 503 naming the database.
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
from pathlib import Path

import httpx
import pytest
import sqlalchemy as sa
from websockets.sync.client import connect as ws_connect

from service.jobs.points import store_point
from service.storage.engine import make_engine
from service.storage.migrate import upgrade
from service.storage.samples import Sample, count_samples
from service.storage.store import Store
from service.storage.writer import SampleWriter
from tests.helpers.fleet import UNREACHABLE, Daemon
from tests.helpers.pg_proxy import PgProxy
from tests.helpers.waiting import eventually

pytestmark = [pytest.mark.postgres]

GRID = {"x_deg": [-1.0, 1.0], "y_deg": [-1.0, 1.0], "n_x": 3, "n_y": 3}
SETTLE = {"tolerance_deg": 0.002, "window_s": 1.0, "timeout_s": 600.0}
SAMPLES_PER_POINT = 6
# TILTLAB_DB_OUTAGE_S of the daemon under test: well past the 10-s outage below, on a busy machine
# too
OUTAGE_LIMIT_S = 20


@pytest.fixture
def migrated(database_url: str) -> str:
    engine = make_engine(database_url)
    upgrade(engine)
    engine.dispose()
    return database_url


def _samples(device_id: int, n: int, t0: float) -> list[Sample]:
    return [Sample(device_id, t0 + i * 0.01, 0.001 * i, -0.001 * i, None, 21.5) for i in range(n)]


def test_sample_writer_keeps_what_it_took_through_an_outage(migrated: str, proxy: PgProxy) -> None:
    direct = make_engine(migrated)
    device = Store(direct).devices.add_device("NS-25/E2", "SN-OUT-1", "dut", actor="test")
    engine = make_engine(proxy.url_of(migrated), connect_args={"connect_timeout": 2})
    writer = SampleWriter(engine, capacity=500, batch_size=100, put_timeout_s=2.0)
    try:
        before = _samples(device.id, 300, 1_000.0)
        assert writer.put_many(before) == 300
        writer.flush(timeout=30)

        proxy.cut()
        # more than the queue holds while the database is away
        during = _samples(device.id, 800, 2_000.0)
        taken = writer.put_many(during[:100])  # the writer finds the database away with these
        eventually(
            lambda: writer.database.up,
            until=lambda up: not up,
            timeout_s=20,
            every_s=0.05,
            what="the writer seeing the database down",
        )
        taken += writer.put_many(during[100:])
        # the newest refused, counted, never waited for
        assert writer.dropped == len(during) - taken > 0
        assert writer.pending == taken  # everything taken waits, nothing given up
        time.sleep(1.0)
        proxy.restore()
        writer.flush(timeout=30)
        assert writer.database.up

        with direct.connect() as conn:
            stored = [
                tuple(r)
                for r in conn.execute(
                    sa.text(
                        "SELECT t_s, count(*) FROM samples WHERE device_id = :d GROUP BY t_s ORDER "
                        "BY t_s"
                    ),
                    {"d": device.id},
                )
            ]
        assert all(n == 1 for _, n in stored), "a sample stored twice"
        # in order, the oldest kept
        assert [t for t, _ in stored] == [s.t_s for s in before + during[:taken]]
    finally:
        writer.close(timeout=30)
        engine.dispose()
        direct.dispose()


def test_a_commit_whose_answer_was_lost_is_not_written_twice(migrated: str, proxy: PgProxy) -> None:
    direct = make_engine(migrated)
    store = Store(direct)
    device = store.devices.add_device("NS-25/E2", "SN-OUT-2", "dut", actor="test")
    engine = make_engine(proxy.url_of(migrated), connect_args={"connect_timeout": 2})
    writer = SampleWriter(engine, capacity=500, batch_size=200)
    try:
        proxy.lose_next_commit_answer = True
        writer.put_many(_samples(device.id, 200, 3_000.0))
        writer.flush(timeout=30)
        # the server committed, the writer heard nothing and tried again
        assert proxy.commit_answers_lost == 1
        with direct.connect() as conn:
            assert count_samples(conn, device_id=device.id) == 200
    finally:
        writer.close(timeout=30)
        engine.dispose()

    # a job's point (samples and settled means) written again after such a loss is stored once
    job = store.jobs.create_job(device.id, "stage", "kinematic", actor="test")
    store.jobs.start_job(job.id, actor="test")
    rows = [
        s._replace(job_id=job.id, point=0, source="calibration")
        for s in _samples(device.id, 10, 4_000.0)
    ]
    settled = {
        device.id: {
            "point": 0,
            "cmd_x_deg": 0.0,
            "cmd_y_deg": 0.0,
            "n_samples": 10,
            "t_start_s": 4_000.0,
            "t_end_s": 4_000.09,
            "ch_x_mean": 0.0045,
            "ch_y_mean": -0.0045,
            "ch_z_mean": None,
            "ch_x_std": 0.003,
            "ch_y_std": 0.003,
            "ch_z_std": None,
            "temp_c_mean": 21.5,
        }
    }
    store_point(store, job.id, 0, rows, settled)  # type: ignore[arg-type]
    store_point(store, job.id, 0, rows, settled)  # type: ignore[arg-type]
    with direct.connect() as conn:
        assert count_samples(conn, job_id=job.id) == 10
    assert len(store.points.settled_points(job.id)) == 1
    direct.dispose()


def _job(url: str, auth: dict[str, str], job_id: int) -> dict:
    return httpx.get(f"{url}/calibrations/{job_id}", headers=auth, timeout=10).json()


def _start_job(url: str, auth: dict[str, str]) -> int:
    answer = httpx.post(
        f"{url}/calibrations",
        headers=auth,
        timeout=30,
        json={
            "procedure": "stage-grid",
            "method": "kinematic",
            "grid": GRID,
            "samples_per_point": SAMPLES_PER_POINT,
            "validation": {"n_points": 1},
            "settle": SETTLE,
        },
    )
    assert answer.status_code == 202, answer.text
    job_id = int(answer.json()["id"])
    eventually(
        lambda: _job(url, auth, job_id),
        until=lambda j: j["state"] == "running" and j["progress"]["points_done"] >= 1,
        timeout_s=60,
        every_s=0.1,
        ignoring=UNREACHABLE,
        what="the job running with a point done",
    )
    return job_id


def _health(url: str) -> dict:
    return httpx.get(f"{url}/health", timeout=10).json()


def test_daemon_waits_through_an_outage_and_fails_a_job_only_past_the_limit(
    tmp_path: Path, migrated: str, proxy: PgProxy
) -> None:
    env = {
        "TILTLAB_DATABASE_URL": proxy.url_of(migrated),
        "TILTLAB_SIM_SPEED": "20",
        "TILTLAB_DB_OUTAGE_S": str(OUTAGE_LIMIT_S),
    }
    with Daemon(tmp_path / "a", env) as daemon, contextlib.ExitStack() as streams:
        url = daemon.url
        auth = {"Authorization": f"Bearer {(tmp_path / 'a' / 'admin.token').read_text().strip()}"}
        # the admin token signs approvals below: it names its person (a token without one is refused
        # with 403)
        assert (
            httpx.patch(
                f"{url}/tokens/admin",
                headers=auth,
                timeout=10,
                json={"person": {"name": "Dr. Alice Example", "function": "Head of Laboratory"}},
            ).status_code
            == 200
        )

        # --- a 10-s outage in the middle of a job: the daemon serves, says so, and the job goes on
        job_id = _start_job(url, auth)
        token = auth["Authorization"].split()[1]
        phases: list[str | None] = []  # the job's stream, heard through the outage
        stream = streams.enter_context(
            ws_connect(f"{url.replace('http', 'ws')}/ws/jobs/{job_id}?token={token}")
        )
        assert json.loads(stream.recv(timeout=10))["type"] == "snapshot"

        def listen() -> None:
            for message in stream:
                body = json.loads(message)
                if body["type"] in ("job", "end"):
                    phases.append(body["job"]["progress"]["phase"])

        listener = threading.Thread(target=listen, daemon=True)
        listener.start()
        proxy.cut()
        cut_at = time.monotonic()
        away = eventually(
            lambda: _health(url),
            until=lambda h: (
                h["database_state"] == "away" and job_id in h["database_outage"]["jobs_waiting"]
            ),
            timeout_s=8,
            every_s=0.1,
            ignoring=UNREACHABLE,
            what="the daemon saying the database is away, the job waiting",
        )
        assert (
            away["status"] == "degraded"
            and away["database_outage"]["outage_limit_s"] == OUTAGE_LIMIT_S
        )
        assert away["database_outage"]["writes_waiting"] >= 1
        # said inside the 10 s, so that the outage ends well before the limit however busy the
        # machine
        metrics = httpx.get(f"{url}/metrics", headers=auth, timeout=10)
        assert metrics.status_code == 200 and "tiltlab_database_up 0.0" in metrics.text
        unreadable = httpx.get(f"{url}/calibrations/{job_id}", headers=auth, timeout=10)
        assert (
            unreadable.status_code == 503 and unreadable.json()["title"] == "Database unreachable"
        )

        def served_10_s_into_the_outage() -> bool:
            if time.monotonic() - cut_at >= 10:
                return True
            tilt = httpx.get(f"{url}/tilt", headers=auth, timeout=5)
            assert tilt.status_code == 200, tilt.text  # the bench is served through the outage
            return False

        eventually(
            served_10_s_into_the_outage,
            timeout_s=30,
            every_s=0.5,
            what="10 s of /tilt served through the outage",
        )
        outage_s = time.monotonic() - cut_at
        assert outage_s < OUTAGE_LIMIT_S - 2, f"the test's own outage ran {outage_s:.1f} s"
        proxy.restore()

        job = eventually(
            lambda: _job(url, auth, job_id),
            until=lambda j: j["state"] not in ("queued", "running"),
            timeout_s=90,
            every_s=0.2,
            ignoring=UNREACHABLE,
            what="the job ended",
        )
        assert job["state"] == "succeeded", job["error"]
        listener.join(timeout=20)
        stream.close()
        assert "waiting for the database" in phases  # the job's stream said why it paused
        assert phases[-1] == "done"
        assert (
            eventually(
                lambda: _health(url),
                until=lambda h: h["database_state"] == "up",
                timeout_s=30,
                every_s=0.2,
                ignoring=UNREACHABLE,
                what="the database up again",
            )["status"]
            == "ok"
        )
        direct = make_engine(migrated)
        with direct.connect() as conn:
            total, distinct = conn.execute(
                sa.text(
                    "SELECT count(*), count(DISTINCT (device_id, t_s)) FROM samples WHERE "
                    "job_id = :j"
                ),
                {"j": job_id},
            ).one()
        points = 3 * 3 + 1
        # every sample of every point, each once
        assert total == distinct == points * 2 * SAMPLES_PER_POINT
        record_id = job["record"]["id"]

        # --- an outage longer than TILTLAB_DB_OUTAGE_S: the job fails naming it, what it stored is
        # kept
        job_id = _start_job(url, auth)
        proxy.cut()
        eventually(
            lambda: _health(url),
            until=lambda h: job_id in (h["database_outage"] or {}).get("jobs_waiting", []),
            timeout_s=8,
            every_s=0.1,
            ignoring=UNREACHABLE,
            what="the job waiting for the database",
        )
        refused = httpx.post(
            f"{url}/records/{record_id}/approve",
            headers=auth,
            json={"meaning": "approval"},
            timeout=10,
        )
        assert refused.status_code == 503, refused.text
        assert refused.headers["content-type"].startswith("application/problem+json")
        assert (
            "database" in refused.json()["detail"]
            and refused.json()["title"] == "Database unreachable"
        )
        eventually(
            lambda: _health(url),
            until=lambda h: (
                h["database_state"] == "away" and job_id not in h["database_outage"]["jobs_waiting"]
            ),
            timeout_s=OUTAGE_LIMIT_S + 10,
            every_s=0.2,
            ignoring=UNREACHABLE,
            what="the job given up past the outage limit",
        )
        assert httpx.get(f"{url}/tilt", headers=auth, timeout=5).status_code == 200
        proxy.restore()
        job = eventually(
            lambda: _job(url, auth, job_id),
            until=lambda j: j["state"] not in ("queued", "running"),
            timeout_s=30,
            every_s=0.2,
            ignoring=UNREACHABLE,
            what="the job ended",
        )
        assert job["state"] == "failed" and job["error"].startswith("database_unreachable:"), job
        assert job["progress"]["points_done"] >= 1
        with direct.connect() as conn:
            kept = conn.execute(
                sa.text("SELECT count(DISTINCT point) FROM settled_points WHERE job_id = :j"),
                {"j": job_id},
            ).scalar_one()
        assert kept >= 1
        direct.dispose()
