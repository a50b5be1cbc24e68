"""Calibration jobs and their state machine; every transition is audited."""

from __future__ import annotations

from collections.abc import Mapping

import sqlalchemy as sa

from service.errors import InputError
from service.storage.errors import IllegalTransition, UnknownEntity
from service.storage.models import Bench, CalibrationJob, Order, utc_now
from service.storage.store.base import StoreBase
from service.storage.store.checks import _doc, _finite, _text

# queued -> running -> succeeded | failed | cancelled; a queued job may also be cancelled or fail to start.
TRANSITIONS: dict[str, frozenset[str]] = {
    "queued": frozenset({"running", "cancelled", "failed"}),
    "running": frozenset({"succeeded", "failed", "cancelled"}),
    "succeeded": frozenset(),
    "failed": frozenset(),
    "cancelled": frozenset(),
}
TERMINAL = frozenset(s for s, nxt in TRANSITIONS.items() if not nxt)


class JobsStore(StoreBase):
    def create_job(
        self,
        device_id: int,
        kind: str,
        method: str,
        *,
        actor: str,
        parameters: Mapping | None = None,
        bench_id: int | None = None,
        order_id: int | None = None,
    ) -> CalibrationJob:
        with self._tx() as s:
            self._device(s, device_id)
            if bench_id is not None and s.get(Bench, bench_id) is None:
                raise UnknownEntity(f"bench {bench_id} does not exist")
            if order_id is not None and s.get(Order, order_id) is None:
                raise UnknownEntity(f"order {order_id} does not exist")
            job = CalibrationJob(
                device_id=device_id,
                bench_id=bench_id,
                kind=_text("kind", kind, 40),
                method=_text("method", method, 80),
                state="queued",
                progress=0.0,
                parameters=_doc("parameters", parameters or {}),
                created_by=_text("actor", actor),
                order_id=order_id,
            )
            s.add(job)
            s.flush()
            self._audit(s, actor, "job.create", "job", job.id, {"device_id": device_id, "kind": kind, "method": method})
            return job

    def get_job(self, job_id: int) -> CalibrationJob:
        with self._read() as s:
            return self._job(s, job_id)

    def jobs(self, *, state: str | None = None) -> list[CalibrationJob]:
        with self._read() as s:
            stmt = sa.select(CalibrationJob).order_by(CalibrationJob.id)
            if state is not None:
                stmt = stmt.where(CalibrationJob.state == state)
            return list(s.scalars(stmt))

    def job_counts_by_state(self) -> dict[str, int]:
        """How many jobs are in each state (one grouped query; for the daemon's metrics)."""
        with self._read() as s:
            rows = s.execute(sa.select(CalibrationJob.state, sa.func.count()).group_by(CalibrationJob.state))
            return {str(state): int(n) for state, n in rows}

    def transition_job(
        self, job_id: int, to_state: str, *, actor: str, failure_reason: str | None = None
    ) -> CalibrationJob:
        if to_state not in TRANSITIONS:
            raise InputError(f"job state {to_state!r} is not one of {sorted(TRANSITIONS)}")
        with self._tx() as s:
            job = self._job(s, job_id)
            if to_state not in TRANSITIONS[job.state]:
                allowed = ", ".join(sorted(TRANSITIONS[job.state])) or "none (terminal state)"
                raise IllegalTransition(f"job {job_id}: {job.state} -> {to_state} is not allowed; allowed: {allowed}")
            if to_state == "failed":
                failure_reason = _text("failure_reason", failure_reason, 10_000)
            elif failure_reason is not None and to_state != "cancelled":
                raise InputError(f"a failure_reason belongs to a failed or cancelled job, not {to_state}")
            now = utc_now()
            previous = job.state
            job.state = to_state
            if to_state == "running":
                job.started_at = now
            if to_state in TERMINAL:
                job.finished_at = now
                job.failure_reason = failure_reason
                if to_state == "succeeded":
                    job.progress = 1.0
                    job.phase = "done"  # a failed or cancelled job keeps the phase it ended in
            self._audit(
                s, actor, f"job.{to_state}", "job", job.id,
                {"from": previous, "to": to_state, "failure_reason": failure_reason},
            )  # fmt: skip
            return job

    def start_job(self, job_id: int, *, actor: str) -> CalibrationJob:
        return self.transition_job(job_id, "running", actor=actor)

    def succeed_job(self, job_id: int, *, actor: str) -> CalibrationJob:
        return self.transition_job(job_id, "succeeded", actor=actor)

    def fail_job(self, job_id: int, reason: str, *, actor: str) -> CalibrationJob:
        return self.transition_job(job_id, "failed", actor=actor, failure_reason=reason)

    def cancel_job(self, job_id: int, *, actor: str, reason: str | None = None) -> CalibrationJob:
        return self.transition_job(job_id, "cancelled", actor=actor, failure_reason=reason)

    def set_progress(self, job_id: int, progress: float) -> None:
        """Progress of a running job in [0, 1]; not audited (it is not a decision, only a gauge)."""
        value = _finite("progress", progress, optional=False)
        if not 0.0 <= value <= 1.0:  # type: ignore[operator]
            raise InputError(f"progress {progress} is outside [0, 1]")
        with self._tx() as s:
            job = self._job(s, job_id)
            if job.state != "running":
                raise IllegalTransition(f"job {job_id} is {job.state}; progress is only kept for running jobs")
            job.progress = value  # type: ignore[assignment]
