"""Two requests with one Idempotency-Key at the same moment make one job and both answer it; a job
cancelled or stopped is audited with the person who did it."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import sqlalchemy as sa

from tests.helpers.waiting import eventually

GRID = {"x_deg": [-1.0, 1.0], "y_deg": [-1.0, 1.0], "n_x": 3, "n_y": 3}
BODY = {
    "procedure": "stage-grid",
    "method": "kinematic",
    "grid": GRID,
    "samples_per_point": 4,
    "validation": {"n_points": 1},
}


def _count(client, table: str) -> int:
    with client.app.state.engine.connect() as c:
        return c.execute(sa.text(f"SELECT count(*) FROM {table}")).scalar()


def test_concurrent_repeats_of_one_idempotency_key_answer_the_first_job(daemon, monkeypatch):
    client, h = daemon
    jobs = client.app.state.jobs
    plan, create = jobs.admission.plan, jobs.store.jobs.create_calibration_job
    planned = threading.Semaphore(0)

    def counted_plan(*args, **kwargs):  # type: ignore[no-untyped-def]
        try:
            return plan(*args, **kwargs)
        finally:
            planned.release()

    def create_once_both_are_admitted(*args, **kwargs):  # type: ignore[no-untyped-def]
        # The first job is written only after the second request has passed admission: the second
        # then meets the bench taken by a job still being written.
        assert planned.acquire(timeout=60) and planned.acquire(timeout=60)
        return create(*args, **kwargs)

    monkeypatch.setattr(jobs.admission, "plan", counted_plan)
    monkeypatch.setattr(jobs.store.jobs, "create_calibration_job", create_once_both_are_admitted)
    jobs_before, keys_before = (
        _count(client, "calibration_jobs"),
        _count(client, "idempotency_keys"),
    )
    headers = {**h, "Idempotency-Key": "same-moment"}
    with ThreadPoolExecutor(2) as pool:
        answers = list(
            pool.map(lambda _: client.post("/calibrations", headers=headers, json=BODY), range(2))
        )
    assert sorted(r.status_code for r in answers) == [200, 202], [r.text for r in answers]
    assert answers[0].json()["id"] == answers[1].json()["id"]
    assert all(r.headers["Location"] == f"/calibrations/{answers[0].json()['id']}" for r in answers)
    assert _count(client, "calibration_jobs") == jobs_before + 1
    assert _count(client, "idempotency_keys") == keys_before + 1


def _operator(client, name: str) -> dict[str, str]:
    _, token = client.app.state.store.tokens.create_token(name, "operate", actor="test")
    return {"Authorization": f"Bearer {token}"}


def _audited(client, job_id: int, action: str):  # type: ignore[no-untyped-def]
    events = client.app.state.store.audit.events(entity="job", entity_id=job_id)
    return [e for e in events if e.action == action]


def test_cancel_is_audited_with_the_person_who_cancelled(daemon):
    client, h = daemon
    alice = _operator(client, "alice")
    job_id = client.post("/calibrations", headers=h, json=BODY).json()["id"]
    r = client.post(f"/calibrations/{job_id}/cancel", headers=alice)
    assert r.status_code == 200 and r.json()["state"] == "cancelled", r.text
    [event] = _audited(client, job_id, "job.cancelled")
    assert event.actor == "alice"
    assert event.details["failure_reason"] == "cancelled by alice"


def test_stop_is_audited_with_the_person_who_stopped(daemon):
    client, h = daemon
    bench = client.app.state.bench
    bob = _operator(client, "bob")
    job_id = client.post("/calibrations", headers=h, json=BODY).json()["id"]
    eventually(
        lambda: client.get(f"/calibrations/{job_id}", headers=h).json()["state"] == "running",
        timeout_s=60,
        every_s=0.02,
        what=f"job {job_id} running",
    )
    r = client.post("/stage/stop", headers=bob, json={"bench": bench.name})
    assert r.status_code == 200 and r.json()["failed_job"] == job_id, r.text
    job = client.get(f"/calibrations/{job_id}", headers=h).json()
    assert job["state"] == "failed" and "(bob)" in job["error"], job
    [event] = _audited(client, job_id, "job.failed")
    assert event.actor == "bob"
