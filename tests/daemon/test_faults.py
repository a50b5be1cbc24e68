"""Faults: a sensor lost mid-job, stop during a move, and a daemon killed mid-job then resumed."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time

import httpx
import sqlalchemy as sa
from scipy import stats

from service.calibration.methods.stage.common import MEAS_NAMES
from service.calibration.uncertainty import welch_satterthwaite
from service.instruments import controller
from tests.helpers.daemon import wait_bench_seconds, wait_job
from tests.helpers.processes import spawn
from tests.helpers.running_service import free_port
from tests.helpers.waiting import eventually

GRID = {"x_deg": [-2.0, 2.0], "y_deg": [-2.0, 2.0], "n_x": 3, "n_y": 3}
BODY = {
    "procedure": "stage-grid",
    "method": "kinematic",
    "grid": GRID,
    "samples_per_point": 6,
    "validation": {"n_points": 2},
}


def _wait_points(get, n, timeout_s=120.0) -> dict:
    return eventually(
        get,
        until=lambda job: (
            job["progress"]["points_done"] >= n or job["state"] not in ("queued", "running")
        ),
        timeout_s=timeout_s,
        every_s=0.05,
        what=f"{n} points done, or the job ended",
    )


def _settled(engine, job_id) -> int:
    with engine.connect() as c:
        return c.execute(
            sa.text("SELECT count(*) FROM settled_points WHERE job_id = :j"), {"j": job_id}
        ).scalar()


def test_sensor_lost_mid_job_fails_it_naming_role_and_port_and_keeps_points(daemon):
    client, h = daemon
    bench = client.app.state.bench
    job_id = client.post("/calibrations", headers=h, json=BODY).json()["id"]
    _wait_points(lambda: client.get(f"/calibrations/{job_id}", headers=h).json(), 2)
    bench.sim.faults("measurement_sensor").disconnect(4.0)
    job = wait_job(client, job_id, h)
    port = bench.port_of("measurement_sensor")
    assert (
        job["state"] == "failed" and "measurement_sensor" in job["error"] and port in job["error"]
    ), job
    assert _settled(client.app.state.engine, job_id) >= 4  # two sensors per measured point, kept
    eventually(
        lambda: {d["role"]: d for d in client.get("/devices", headers=h).json()["devices"]},
        until=lambda devs: (
            devs["measurement_sensor"]["state"] == "connected"
            and devs["measurement_sensor"]["counters"]["reconnects"] >= 1
        ),
        timeout_s=60,
        every_s=0.2,
        what="the measurement sensor reconnected",
    )
    again = client.post("/calibrations", headers=h, json=BODY)
    assert again.status_code == 202, again.text
    assert wait_job(client, again.json()["id"], h)["state"] == "succeeded"


def test_stop_during_a_move_acts_at_once_and_fails_the_job(daemon):
    client, h = daemon
    bench = client.app.state.bench
    job_id = client.post("/calibrations", headers=h, json=BODY).json()["id"]
    # catch it mid-move
    eventually(lambda: bench.pose.moving, timeout_s=30, every_s=0.005, what="the stage moving")
    r = client.post("/stage/stop", headers=h, json={})
    assert r.status_code == 200 and r.json()["failed_job"] == job_id
    job = client.get(f"/calibrations/{job_id}", headers=h).json()
    assert job["state"] == "failed" and "stopped by POST /stage/stop" in job["error"], job
    world = bench.sim.world
    # ST is not answered (no set command of the controller is): the answer says it was sent to every
    # axis, and the controller stops when it reads it, on a loaded machine a moment after the answer
    eventually(
        lambda: all(a.state == controller.STATE_READY for a in world.axes.values()),
        timeout_s=10,
        what="the axes standing after POST /stage/stop",
    )
    pose = world.pose_deg
    wait_bench_seconds(bench, 6.0)
    assert world.pose_deg == pose  # standing: nothing the job had sent moves it again
    assert all(a.state == controller.STATE_READY for a in world.axes.values())
    # the bench is free again
    assert client.get("/benches", headers=h).json()["benches"][0]["held_by"] is None


def test_stop_names_the_job_even_when_the_job_ends_before_the_stop_returns(daemon):
    """The job sees its move stopped and ends, letting go of the bench, while the stop is still
    being sent: the stop still names it, and the job's error says it was stopped by request."""
    import asyncio

    client, h = daemon
    bench = client.app.state.bench
    jobs = client.app.state.jobs
    job_id = client.post("/calibrations", headers=h, json=BODY).json()["id"]
    eventually(lambda: bench.pose.moving, timeout_s=30, every_s=0.005, what="the stage moving")
    stop = bench.stop

    async def stop_then_let_the_job_end_first():
        await stop()
        await asyncio.wait({jobs.tasks[job_id]}, timeout=10.0)

    bench.stop = stop_then_let_the_job_end_first
    r = client.post("/stage/stop", headers=h, json={})
    assert jobs.tasks[job_id].done()  # the job had ended before the route looked again
    assert r.status_code == 200 and r.json()["failed_job"] == job_id, r.json()
    job = client.get(f"/calibrations/{job_id}", headers=h).json()
    assert job["state"] == "failed" and "stopped by POST /stage/stop" in job["error"], job
    assert not jobs.stop_reasons  # nothing left behind for a later job


def test_stop_answers_after_the_job_s_end_is_written(daemon, monkeypatch):
    """The job sees its move stopped and is writing its end, in a worker thread a slow disk holds
    up, when the stop cancels it: the stop answers only once that write has landed, so the job read
    right after is failed, with the reason."""
    import asyncio
    import threading

    client, h = daemon
    bench = client.app.state.bench
    store = client.app.state.jobs.store
    fail_job, writing = store.jobs.fail_job, threading.Event()

    def slow_fail_job(*args, **kwargs):  # type: ignore[no-untyped-def]
        writing.set()
        time.sleep(0.5)
        return fail_job(*args, **kwargs)

    monkeypatch.setattr(store.jobs, "fail_job", slow_fail_job)
    stop = bench.stop

    async def stop_then_wait_for_the_job_to_write_its_end():
        await stop()
        assert await asyncio.to_thread(writing.wait, 30.0), "the job never wrote its end"

    job_id = client.post("/calibrations", headers=h, json=BODY).json()["id"]
    eventually(lambda: bench.pose.moving, timeout_s=30, every_s=0.005, what="the stage moving")
    bench.stop = stop_then_wait_for_the_job_to_write_its_end
    r = client.post("/stage/stop", headers=h, json={})
    assert r.status_code == 200 and r.json()["failed_job"] == job_id
    job = client.get(f"/calibrations/{job_id}", headers=h).json()
    assert job["state"] == "failed" and "stopped by POST /stage/stop" in job["error"], job


def _standard_uncertainty(model: dict, name: str) -> tuple[float, float]:
    """A record's standard uncertainty of a free parameter and its degrees of freedom: the
    measurement sensor's mounting from its own fit's covariance, the stage's from the chain's."""
    cov = model["covariance"]
    i = cov["names"].index(name)
    fit = model["fit"]
    dof = fit["meas"]["covariance_dof"] if name in MEAS_NAMES else fit["chain"]["dof"]
    return math.sqrt(cov["matrix"][i][i]), float(dof)


class _Daemon:
    def __init__(self, data_dir) -> None:
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.proc = spawn(
            [
                sys.executable,
                "-m",
                "service",
                "serve",
                "--port",
                str(self.port),
                "--sim-speed",
                "20",
            ],
            env={**os.environ, "TILTLAB_DATA_DIR": str(data_dir)},
            stdout=subprocess.DEVNULL,
            stderr=open(data_dir / f"daemon-{self.port}.log", "w"),
        )

        def answers() -> bool:
            assert self.proc.poll() is None, "daemon did not start: it exited"
            httpx.get(f"{self.base}/health", timeout=2)
            return True

        eventually(
            answers,
            timeout_s=60,
            every_s=0.2,
            ignoring=(httpx.TransportError,),
            what="the daemon answering /health",
        )
        self.h = {"Authorization": "Bearer " + (data_dir / "admin.token").read_text().strip()}

    def get(self, path):
        return httpx.get(self.base + path, headers=self.h, timeout=10)

    def post(self, path, json=None):
        return httpx.post(self.base + path, headers=self.h, json=json, timeout=120)

    def wait(self, job_id):
        return eventually(
            lambda: self.get(f"/calibrations/{job_id}").json(),
            until=lambda job: job["state"] in ("succeeded", "failed", "cancelled"),
            timeout_s=240,
            every_s=0.2,
            what=f"job {job_id} ended",
        )

    def stop(self):
        self.proc.terminate()
        self.proc.wait(timeout=30)


def test_sigkill_mid_job_restart_and_resume_matches_an_uninterrupted_run(tmp_path):
    d = _Daemon(tmp_path)
    try:
        job_id = d.post("/calibrations", BODY).json()["id"]
        _wait_points(lambda: d.get(f"/calibrations/{job_id}").json(), 4)
        d.proc.send_signal(signal.SIGKILL)
        d.proc.wait(timeout=10)
    except BaseException:
        d.stop()
        raise
    d = _Daemon(tmp_path)
    try:
        job = d.get(f"/calibrations/{job_id}").json()
        assert job["state"] == "failed" and job["interrupted"] and "interrupted" in job["error"], (
            job
        )
        assert not d.get("/calibrations?state=running").json()["jobs"]
        done_before = job["progress"]["points_done"]
        assert done_before >= 4
        r = d.post(f"/calibrations/{job_id}/resume")
        assert r.status_code == 202, r.text
        resumed = d.wait(job_id)
        assert resumed["state"] == "succeeded", resumed["error"]
        full_id = d.post("/calibrations", BODY).json()["id"]
        full = d.wait(full_id)
        assert full["state"] == "succeeded", full
        ma = d.get(f"/records/{resumed['record']['id']}/model").json()
        mb = d.get(f"/records/{full['record']['id']}/model").json()
        # the resumed record has every grid point once: those stored before the kill and the rest
        assert ma["fit"]["n_points"] == mb["fit"]["n_points"] == GRID["n_x"] * GRID["n_y"]
        a, b = ma["parameters"], mb["parameters"]
        assert a.keys() == b.keys()
        free = [name for name in a if not a[name].get("fixed")]
        for name in a:
            if name not in free:
                assert a[name]["value"] == b[name]["value"]
        # Two runs of the same grid differ by the reading noise and the stage's positioning only,
        # so each free parameter's difference over the two records' combined standard uncertainty
        # is Student-t distributed with the records' degrees of freedom (Welch-Satterthwaite of the
        # two; a 3 x 3 grid leaves the mounting's covariance 6 of them). The bound is that t's
        # quantile at a false-failure rate of 1e-3 over all free parameters (Bonferroni). One
        # record's uncertainty alone, estimated from 6 degrees of freedom, failed a correct resume
        # in 2 of 27 runs.
        tail = 1e-3 / len(free) / 2
        for name in free:
            u_a, nu_a = _standard_uncertainty(ma, name)
            u_b, nu_b = _standard_uncertainty(mb, name)
            u_diff = math.hypot(u_a, u_b)
            # two records, two independent estimates of their noise
            nu = float(welch_satterthwaite([(u_a**2, nu_a), (u_b**2, nu_b)], same_dof_shared=False))
            bound = float(stats.t.isf(tail, nu))
            difference = a[name]["value"] - b[name]["value"]
            assert abs(difference) <= bound * u_diff, (name, difference, u_a, u_b, nu, bound)
        assert d.post(f"/calibrations/{full_id}/resume").status_code == 409
    finally:
        d.stop()
