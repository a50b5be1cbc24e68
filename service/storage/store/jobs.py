"""Calibration jobs: their state machine (every transition audited) and what the daemon keeps of
them beyond it: progress at every step, the Idempotency-Key of the request that created a job,
interruption by a restart and resumption."""

from __future__ import annotations

import datetime as dt
from collections.abc import Collection, Mapping

import sqlalchemy as sa

from service.errors import InputError
from service.storage.canonical import sha256_hex
from service.storage.errors import ConflictError, IllegalTransition, UnknownEntity
from service.storage.models import Bench, CalibrationJob, IdempotencyKey, JobState, Order, utc_now
from service.storage.store.checks import require_doc, require_number, require_text
from service.storage.store.database import Database
from service.storage.store.lookups import device_in, job_in, row_in

# queued -> running -> succeeded | failed | cancelled; a queued job may also be cancelled or fail to
# start.
TRANSITIONS: dict[str, frozenset[str]] = {
    "queued": frozenset({"running", "cancelled", "failed"}),
    "running": frozenset({"succeeded", "failed", "cancelled"}),
    "succeeded": frozenset(),
    "failed": frozenset(),
    "cancelled": frozenset(),
}
TERMINAL = frozenset(state for state, nxt in TRANSITIONS.items() if not nxt)
PHASES = ("homing", "measuring", "fitting", "validating")  # a succeeded job's phase is "done"
INTERRUPTED = (
    "interrupted: the daemon stopped while the job ran; POST /calibrations/{id}/resume continues it"
)


class IdempotencyMismatch(InputError):
    """The same Idempotency-Key came with another body."""


class JobsRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def create_job(
        self,
        device_id: int,
        kind: str,
        method: str,
        *,
        actor: str,
        parameters: Mapping[str, object] | None = None,
        bench_id: int | None = None,
        order_id: int | None = None,
    ) -> CalibrationJob:
        with self._db.transaction() as session:
            device_in(session, device_id)
            if bench_id is not None:
                row_in(session, Bench, bench_id, "bench")
            if order_id is not None:
                row_in(session, Order, order_id, "order")
            job = CalibrationJob(
                device_id=device_id,
                bench_id=bench_id,
                kind=require_text("kind", kind, 40),
                method=require_text("method", method, 80),
                state="queued",
                progress=0.0,
                parameters=require_doc("parameters", parameters or {}),
                created_by=require_text("actor", actor),
                order_id=order_id,
            )
            session.add(job)
            session.flush()
            self._db.audit(
                session,
                actor,
                "job.create",
                "job",
                job.id,
                {"device_id": device_id, "kind": kind, "method": method},
            )
            return job

    def get_job(self, job_id: int) -> CalibrationJob:
        with self._db.session() as session:
            return job_in(session, job_id)

    def all(self, *, state: str | None = None) -> list[CalibrationJob]:
        with self._db.session() as session:
            stmt = sa.select(CalibrationJob).order_by(CalibrationJob.id)
            if state is not None:
                stmt = stmt.where(CalibrationJob.state == state)
            return list(session.scalars(stmt))

    def job_counts_by_state(self) -> dict[str, int]:
        """How many jobs are in each state (one grouped query; for the daemon's metrics)."""
        with self._db.session() as session:
            rows = session.execute(
                sa.select(CalibrationJob.state, sa.func.count()).group_by(CalibrationJob.state)
            )
            return {str(state): int(n) for state, n in rows}

    def transition_job(
        self, job_id: int, to_state: str, *, actor: str, failure_reason: str | None = None
    ) -> CalibrationJob:
        if to_state not in TRANSITIONS:
            raise InputError(f"job state {to_state!r} is not one of {sorted(TRANSITIONS)}")
        with self._db.transaction() as session:
            job = job_in(session, job_id)
            if to_state not in TRANSITIONS[job.state]:
                allowed = ", ".join(sorted(TRANSITIONS[job.state])) or "none (terminal state)"
                raise IllegalTransition(
                    f"job {job_id}: {job.state} -> {to_state} is not allowed; allowed: {allowed}"
                )
            if to_state == JobState.FAILED:
                failure_reason = require_text("failure_reason", failure_reason, 10_000)
            elif failure_reason is not None and to_state != JobState.CANCELLED:
                raise InputError(
                    f"a failure_reason belongs to a failed or cancelled job, not {to_state}"
                )
            now = utc_now()
            previous = job.state
            job.state = to_state
            if to_state == JobState.RUNNING:
                job.started_at = now
            if to_state in TERMINAL:
                job.finished_at = now
                job.failure_reason = failure_reason
                if to_state == JobState.SUCCEEDED:
                    job.progress = 1.0
                    job.phase = "done"  # a failed or cancelled job keeps the phase it ended in
            self._db.audit(
                session,
                actor,
                f"job.{to_state}",
                "job",
                job.id,
                {"from": previous, "to": to_state, "failure_reason": failure_reason},
            )
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
        value = require_number("progress", progress)
        if not 0.0 <= value <= 1.0:
            raise InputError(f"progress {progress} is outside [0, 1]")
        with self._db.transaction() as session:
            job = job_in(session, job_id)
            if job.state != JobState.RUNNING:
                raise IllegalTransition(
                    f"job {job_id} is {job.state}; progress is only kept for running jobs"
                )
            job.progress = value

    def create_calibration_job(
        self,
        *,
        bench_id: int,
        device_id: int,
        kind: str,
        method: str,
        parameters: Mapping[str, object],
        actor: str,
        points_total: int,
        idempotency_key: str | None = None,
        request: Mapping[str, object] | None = None,
        order_id: int | None = None,
    ) -> tuple[CalibrationJob, bool]:
        """A queued job, or the job an earlier request with the same Idempotency-Key created (then
        False)."""
        request_sha = sha256_hex(dict(request or {}))
        with self._db.transaction() as session:
            if idempotency_key is not None:
                key = require_text("Idempotency-Key", idempotency_key, 200)
                seen = session.scalar(
                    sa.select(IdempotencyKey).where(
                        IdempotencyKey.route == "calibrations", IdempotencyKey.key == key
                    )
                )
                if seen is not None:
                    if seen.request_sha256 != request_sha:
                        raise IdempotencyMismatch(
                            f"Idempotency-Key {key!r} was used for another request body (job "
                            f"{seen.job_id}); use a new key for a new request"
                        )
                    if seen.job_id is None:
                        raise IdempotencyMismatch(
                            f"Idempotency-Key {key!r} belongs to a request that made no job"
                        )
                    return job_in(session, seen.job_id), False
            job = CalibrationJob(
                device_id=device_id,
                bench_id=bench_id,
                kind=require_text("kind", kind, 40),
                method=require_text("method", method, 80),
                state="queued",
                progress=0.0,
                parameters=require_doc("parameters", parameters),
                created_by=require_text("actor", actor),
                points_total=points_total,
                points_done=0,
                order_id=order_id,
            )
            session.add(job)
            session.flush()
            if idempotency_key is not None:
                session.add(
                    IdempotencyKey(
                        key=idempotency_key,
                        route="calibrations",
                        request_sha256=request_sha,
                        job_id=job.id,
                        created_at=utc_now(),
                    )
                )
            self._db.audit(
                session,
                actor,
                "job.create",
                "job",
                job.id,
                {"device_id": device_id, "kind": kind, "method": method, "bench_id": bench_id},
            )
            return job, True

    def idempotency_key(self, key: str, *, route: str = "calibrations") -> IdempotencyKey | None:
        """What the database knows of a request's Idempotency-Key (its body's SHA-256 and the job it
        made)."""
        with self._db.session() as session:
            return session.scalar(
                sa.select(IdempotencyKey).where(
                    IdempotencyKey.route == route, IdempotencyKey.key == key
                )
            )

    def set_job_progress(
        self,
        job_id: int,
        *,
        points_done: int,
        points_total: int,
        phase: str,
        bench_seconds: dict[str, float] | None = None,
    ) -> None:
        if phase not in PHASES:
            raise InputError(f"phase {phase!r} is not one of {', '.join(PHASES)}")
        with self._db.transaction() as session:
            job = job_in(session, job_id)
            if job.state != JobState.RUNNING:
                raise IllegalTransition(
                    f"job {job_id} is {job.state}; progress is only kept for running jobs"
                )
            job.points_done, job.points_total, job.phase = points_done, points_total, phase
            if bench_seconds is not None:
                job.bench_seconds = dict(bench_seconds)
            job.progress = min(1.0, points_done / points_total) if points_total else 0.0

    def set_bench_seconds(self, job_id: int, bench_seconds: dict[str, float]) -> None:
        """The bench time a job spent in all, kept with the job as it ends (its last points after
        the last progress)."""
        with self._db.transaction() as session:
            job_in(session, job_id).bench_seconds = dict(bench_seconds)

    def mark_interrupted(
        self, *, actor: str, bench_ids: Collection[int] | None = None
    ) -> list[int]:
        """At start-up and shutdown: every job a run left queued or running is failed as
        interrupted; only those of `bench_ids` when given (a node of a fleet: the other nodes' jobs
        are theirs, and may be running)."""
        with self._db.transaction() as session:
            stmt = sa.select(CalibrationJob).where(CalibrationJob.state.in_(("queued", "running")))
            if bench_ids is not None:
                stmt = stmt.where(CalibrationJob.bench_id.in_(list(bench_ids)))
            jobs = list(session.scalars(stmt.order_by(CalibrationJob.id)))
            for job in jobs:
                previous = job.state
                job.state, job.interrupted, job.finished_at = "failed", True, utc_now()
                job.failure_reason = INTERRUPTED.format(id=job.id)
                self._db.audit(
                    session,
                    actor,
                    "job.failed",
                    "job",
                    job.id,
                    {"from": previous, "to": "failed", "failure_reason": job.failure_reason},
                )
            return [j.id for j in jobs]

    def interrupt_job(self, job_id: int, reason: str, *, actor: str) -> CalibrationJob:
        """A queued or running job failed for a cause that leaves its stored points intact (a full
        disk): it may be resumed (POST /calibrations/{id}/resume) once the cause is gone."""
        reason = require_text("failure_reason", reason, 10_000)
        with self._db.transaction() as session:
            job = job_in(session, job_id)
            if job.state not in (JobState.QUEUED, JobState.RUNNING):
                raise IllegalTransition(f"job {job_id}: {job.state} -> failed is not allowed")
            previous = job.state
            job.state, job.interrupted, job.finished_at, job.failure_reason = (
                "failed",
                True,
                utc_now(),
                reason,
            )
            self._db.audit(
                session,
                actor,
                "job.failed",
                "job",
                job.id,
                {"from": previous, "to": "failed", "failure_reason": reason, "resumable": True},
            )
            return job

    def resume_job(self, job_id: int, *, actor: str) -> CalibrationJob:
        """An interrupted job runs again from its stored points."""
        with self._db.transaction() as session:
            job = job_in(session, job_id)
            if not (job.state == JobState.FAILED and job.interrupted):
                raise ConflictError(
                    f"job {job_id} is {job.state}"
                    + ("" if job.state != JobState.FAILED else f" ({job.failure_reason})")
                    + "; only an interrupted job can be resumed"
                )
            job.state, job.interrupted, job.failure_reason, job.finished_at = (
                "running",
                False,
                None,
                None,
            )
            self._db.audit(
                session,
                actor,
                "job.resume",
                "job",
                job.id,
                {"from": "failed", "to": "running", "points_done": job.points_done},
            )
            return job

    def list_jobs(
        self,
        *,
        state: str | None = None,
        bench_id: int | None = None,
        updated_since: dt.datetime | None = None,
        before_id: int | None = None,
        limit: int = 50,
    ) -> list[CalibrationJob]:
        """Newest first; `before_id` is the cursor (the last id of the previous page)."""
        with self._db.session() as session:
            stmt = sa.select(CalibrationJob).order_by(CalibrationJob.id.desc()).limit(limit)
            if state is not None:
                stmt = stmt.where(CalibrationJob.state == state)
            if bench_id is not None:
                stmt = stmt.where(CalibrationJob.bench_id == bench_id)
            if updated_since is not None:
                stmt = stmt.where(CalibrationJob.updated_at >= updated_since)
            if before_id is not None:
                stmt = stmt.where(CalibrationJob.id < before_id)
            return list(session.scalars(stmt))

    def job_or_none(self, job_id: int) -> CalibrationJob | None:
        try:
            return self.get_job(job_id)
        except UnknownEntity:
            return None
