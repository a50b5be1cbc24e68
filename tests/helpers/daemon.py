"""A daemon in the test's own process on a simulated bench (its instruments on in-memory lines
speaking the real bytes, sped up), its admin token, and the waits on what it runs."""

from __future__ import annotations

import time

from fastapi.testclient import TestClient

from service.api.app import create_app
from service.config import Settings
from tests.helpers.waiting import eventually


def make_client(tmp_path, **overrides) -> TestClient:
    """An in-process daemon; its simulated instruments on in-memory lines (the pty is under test in
    tests/instruments and with the daemon in a process of its own, test_faults)."""
    settings = Settings(
        data_dir=tmp_path, **{"sim_speed": 20.0, "sim_transport": "loopback", **overrides}
    )
    return TestClient(create_app(settings))


def admin_headers(tmp_path) -> dict[str, str]:
    return {"Authorization": "Bearer " + (tmp_path / "admin.token").read_text().strip()}


def wait_job(
    client, job_id, headers, states=("succeeded", "failed", "cancelled"), timeout_s=240.0
) -> dict:
    """The job once its state is one of `states`."""
    return eventually(
        lambda: client.get(f"/calibrations/{job_id}", headers=headers).json(),
        until=lambda job: job["state"] in states,
        timeout_s=timeout_s,
        every_s=0.2,
        what=f"job {job_id} in a state of {states}",
    )


def calibrate_and_activate(client, headers, request: dict) -> dict:
    """Run a calibration job to success and make its record the active one; the job as it ended."""
    r = client.post("/calibrations", headers=headers, json=request)
    assert r.status_code == 202, r.text
    job = wait_job(client, r.json()["id"], headers)
    assert job["state"] == "succeeded", job
    assert (
        client.post(f"/records/{job['record']['id']}/activate", headers=headers).status_code == 200
    )
    return job


def fresh_tilt(client, h, attempts: int = 40) -> dict:
    """GET /tilt until it is not stale: a test client sharing its process with a sped-up bench may
    see the reader a few tenths of a second behind on a loaded machine, and /tilt rightly says
    so."""
    for _ in range(attempts):
        t = client.get("/tilt", headers=h).json()
        if not t["stale"]:
            return t
        time.sleep(0.05)
    raise AssertionError(f"every GET /tilt was stale: {t}")


def wait_bench_seconds(bench, seconds: float, timeout_s: float = 30.0) -> None:
    """Until the bench's clock has run `seconds` (bench time), within a real-time deadline."""
    until = bench.clock.monotonic() + seconds
    eventually(
        lambda: bench.clock.monotonic() >= until,
        timeout_s=timeout_s,
        what="the bench clock to advance",
    )


def job_from(
    client, headers, body: dict, stands_at: tuple[float, float]
) -> tuple[dict, dict | None]:
    """A calibration job run to its end with the stage first moved to `stands_at` (where a job
    before might have left it): the job, and its record where it made one."""
    moved = client.post(
        "/stage/move", headers=headers, json={"x_deg": stands_at[0], "y_deg": stands_at[1]}
    )
    assert moved.status_code == 200, moved.text
    r = client.post("/calibrations", headers=headers, json=body)
    assert r.status_code == 202, r.text
    job = wait_job(client, r.json()["id"], headers)
    record = (
        client.get(f"/records/{job['record']['id']}", headers=headers).json()
        if job["record"]
        else None
    )
    return job, record
