"""A daemon on a simulated bench with the real drivers, sped up: in process, its instruments on
in-memory lines speaking the real bytes."""

from __future__ import annotations

import time

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.config import Settings


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
    deadline = time.monotonic() + timeout_s
    while True:
        job = client.get(f"/calibrations/{job_id}", headers=headers).json()
        if job["state"] in states:
            return job
        assert time.monotonic() < deadline, f"job still {job['state']}: {job}"
        time.sleep(0.2)


@pytest.fixture
def daemon(tmp_path):
    with make_client(tmp_path) as client:
        yield client, admin_headers(tmp_path)


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
