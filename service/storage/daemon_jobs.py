"""What the daemon keeps of its jobs beyond the state machine: progress at every step, the
Idempotency-Key of the request that created a job, interruption by a restart and resumption.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping

import sqlalchemy as sa

from service.errors import InputError
from service.storage.canonical import sha256_hex
from service.storage.diagnoses import DiagnosisStore
from service.storage.errors import ConflictError, IllegalTransition, UnknownEntity
from service.storage.lims import LimsStore
from service.storage.models import Bench, CalibrationJob, IdempotencyKey, utc_now
from service.storage.store import Store
from service.storage.store.checks import _doc, _text
from service.storage.tokens import TokenStore

PHASES = ("homing", "measuring", "fitting", "validating")  # a succeeded job's phase is "done"
INTERRUPTED = "interrupted: the daemon stopped while the job ran; POST /calibrations/{id}/resume continues it"


class IdempotencyMismatch(InputError):
    """The same Idempotency-Key came with another body."""


class JobRuntimeStore(Store):
    def ensure_bench(self, name: str, *, actor: str, port: str | None = None) -> Bench:
        with self._read() as s:
            bench = s.scalar(sa.select(Bench).where(Bench.name == name))
        return bench or self.add_bench(name, actor=actor, port=port)

    def create_calibration_job(
        self, *, bench_id: int, device_id: int, kind: str, method: str, parameters: Mapping, actor: str,
        points_total: int, idempotency_key: str | None = None, request: Mapping | None = None,
        order_id: int | None = None,
    ) -> tuple[CalibrationJob, bool]:
        """A queued job, or the job an earlier request with the same Idempotency-Key created (then False)."""
        request_sha = sha256_hex(dict(request or {}))
        with self._tx() as s:
            if idempotency_key is not None:
                key = _text("Idempotency-Key", idempotency_key, 200)
                seen = s.scalar(sa.select(IdempotencyKey).where(IdempotencyKey.route == "calibrations",
                                                                 IdempotencyKey.key == key))
                if seen is not None:
                    if seen.request_sha256 != request_sha:
                        raise IdempotencyMismatch(
                            f"Idempotency-Key {key!r} was used for another request body (job {seen.job_id});"
                            " use a new key for a new request")
                    if seen.job_id is None:
                        raise IdempotencyMismatch(f"Idempotency-Key {key!r} belongs to a request that made no job")
                    return self._job(s, seen.job_id), False
            job = CalibrationJob(device_id=device_id, bench_id=bench_id, kind=_text("kind", kind, 40),
                                 method=_text("method", method, 80), state="queued", progress=0.0,
                                 parameters=_doc("parameters", parameters), created_by=_text("actor", actor),
                                 points_total=points_total, points_done=0, order_id=order_id)
            s.add(job)
            s.flush()
            if idempotency_key is not None:
                s.add(IdempotencyKey(key=idempotency_key, route="calibrations", request_sha256=request_sha,
                                     job_id=job.id, created_at=utc_now()))
            self._audit(s, actor, "job.create", "job", job.id,
                        {"device_id": device_id, "kind": kind, "method": method, "bench_id": bench_id})
            return job, True

    def set_job_progress(self, job_id: int, *, points_done: int, points_total: int, phase: str) -> None:
        if phase not in PHASES:
            raise InputError(f"phase {phase!r} is not one of {', '.join(PHASES)}")
        with self._tx() as s:
            job = self._job(s, job_id)
            if job.state != "running":
                raise IllegalTransition(f"job {job_id} is {job.state}; progress is only kept for running jobs")
            job.points_done, job.points_total, job.phase = points_done, points_total, phase
            job.progress = min(1.0, points_done / points_total) if points_total else 0.0

    def mark_interrupted(self, *, actor: str) -> list[int]:
        """At start-up: every job a previous run left queued or running is failed as interrupted."""
        with self._tx() as s:
            jobs = list(s.scalars(sa.select(CalibrationJob).where(CalibrationJob.state.in_(("queued", "running")))))
            for job in jobs:
                previous = job.state
                job.state, job.interrupted, job.finished_at = "failed", True, utc_now()
                job.failure_reason = INTERRUPTED.format(id=job.id)
                self._audit(s, actor, "job.failed", "job", job.id,
                            {"from": previous, "to": "failed", "failure_reason": job.failure_reason})
            return [j.id for j in jobs]

    def resume_job(self, job_id: int, *, actor: str) -> CalibrationJob:
        """An interrupted job runs again from its stored points."""
        with self._tx() as s:
            job = self._job(s, job_id)
            if not (job.state == "failed" and job.interrupted):
                raise ConflictError(f"job {job_id} is {job.state}" + ("" if job.state != "failed" else
                                    f" ({job.failure_reason})") + "; only an interrupted job can be resumed")
            job.state, job.interrupted, job.failure_reason, job.finished_at = "running", False, None, None
            self._audit(s, actor, "job.resume", "job", job.id, {"from": "failed", "to": "running",
                                                                  "points_done": job.points_done})
            return job

    def list_jobs(self, *, state: str | None = None, bench_id: int | None = None,
                  updated_since: dt.datetime | None = None, before_id: int | None = None,
                  limit: int = 50) -> list[CalibrationJob]:
        """Newest first; `before_id` is the cursor (the last id of the previous page)."""
        with self._read() as s:
            stmt = sa.select(CalibrationJob).order_by(CalibrationJob.id.desc()).limit(limit)
            if state is not None:
                stmt = stmt.where(CalibrationJob.state == state)
            if bench_id is not None:
                stmt = stmt.where(CalibrationJob.bench_id == bench_id)
            if updated_since is not None:
                stmt = stmt.where(CalibrationJob.updated_at >= updated_since)
            if before_id is not None:
                stmt = stmt.where(CalibrationJob.id < before_id)
            return list(s.scalars(stmt))

    def audit_action(self, actor: str, action: str, entity: str, entity_id: object, details: Mapping) -> None:
        """An audit event for an action that changes no row (a stage move, a stop)."""
        with self._tx() as s:
            self._audit(s, actor, action, entity, entity_id, details)

    def job_or_none(self, job_id: int) -> CalibrationJob | None:
        try:
            return self.get_job(job_id)
        except UnknownEntity:
            return None


class DaemonStore(LimsStore, TokenStore, DiagnosisStore, JobRuntimeStore):
    """Everything the daemon writes and reads: the lab's records, its jobs, its tokens and the LIMS tables."""
