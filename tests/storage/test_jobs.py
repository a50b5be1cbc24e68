"""The job state machine: queued -> running -> succeeded | failed | cancelled, nothing else."""

from __future__ import annotations

import pytest

from service.errors import InputError
from service.storage import IllegalTransition, Store, UnknownEntity
from tests.helpers.storage import count


def test_happy_path_with_progress(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    job = store.jobs.create_job(
        device.id, "stage", "kinematic", actor="alice", parameters={"grid": "5x5", "dwell_s": 2}
    )
    assert (job.state, job.progress, job.parameters["grid"]) == ("queued", 0.0, "5x5")
    store.jobs.start_job(job.id, actor="alice")
    store.jobs.set_progress(job.id, 0.5)
    assert store.jobs.get_job(job.id).progress == 0.5
    done = store.jobs.succeed_job(job.id, actor="alice")
    assert (done.state, done.progress) == ("succeeded", 1.0)
    assert done.started_at <= done.finished_at
    actions = [e.action for e in reversed(store.audit.events(entity="job", entity_id=job.id))]
    assert actions == ["job.create", "job.running", "job.succeeded"]


def test_failure_keeps_its_reason(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    job = store.jobs.create_job(device.id, "stage", "kinematic", actor="alice")
    store.jobs.start_job(job.id, actor="alice")
    with pytest.raises(InputError, match="failure_reason"):
        store.jobs.transition_job(job.id, "failed", actor="alice")
    failed = store.jobs.fail_job(job.id, "stage axis B stalled at +4.0 deg", actor="system")
    assert failed.state == "failed" and failed.failure_reason == "stage axis B stalled at +4.0 deg"


@pytest.mark.parametrize(
    ("path", "illegal"),
    [
        ([], "succeeded"),  # queued -> succeeded skips running
        (["running", "succeeded"], "running"),  # terminal states stay terminal
        (["running", "succeeded"], "failed"),
        (["cancelled"], "running"),
        (["running"], "queued"),
        (["running", "failed"], "succeeded"),
    ],
)
def test_illegal_transitions_are_refused(
    store: Store, device, path: list[str], illegal: str
) -> None:  # type: ignore[no-untyped-def]
    job = store.jobs.create_job(device.id, "stage", "kinematic", actor="alice")
    for state in path:
        store.jobs.transition_job(
            job.id, state, actor="alice", failure_reason="x" if state == "failed" else None
        )
    events = count(store.engine, "audit_events")
    with pytest.raises(IllegalTransition, match=f"-> {illegal} is not allowed"):
        store.jobs.transition_job(
            job.id, illegal, actor="alice", failure_reason="x" if illegal == "failed" else None
        )
    assert store.jobs.get_job(job.id).state == (path[-1] if path else "queued")
    assert count(store.engine, "audit_events") == events


def test_progress_only_while_running(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    job = store.jobs.create_job(device.id, "stage", "kinematic", actor="alice")
    with pytest.raises(IllegalTransition, match="queued"):
        store.jobs.set_progress(job.id, 0.1)
    store.jobs.start_job(job.id, actor="alice")
    with pytest.raises(InputError, match="outside"):
        store.jobs.set_progress(job.id, 1.5)
    store.jobs.cancel_job(job.id, actor="alice", reason="operator abort")
    assert store.jobs.get_job(job.id).state == "cancelled"


def test_unknown_job_and_state(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(UnknownEntity, match="job 42"):
        store.jobs.start_job(42, actor="alice")
    job = store.jobs.create_job(device.id, "stage", "kinematic", actor="alice")
    with pytest.raises(InputError, match="not one of"):
        store.jobs.transition_job(job.id, "paused", actor="alice")
    with pytest.raises(UnknownEntity, match="device 7"):
        store.jobs.create_job(7, "stage", "kinematic", actor="alice")
