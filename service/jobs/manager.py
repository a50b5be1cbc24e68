"""Jobs on the daemon's benches: one per bench, every step persisted, interruptible and resumable.

The manager runs a job's life cycle: it admits a request (`admission`), holds the bench, starts
the procedure's task (`registry`: stage grid, the angle procedures), stores its outcome as a record
version, and ends it when it fails, is cancelled, is stopped, or the daemon stops (then the job is
left interrupted, to be resumed from its stored points).
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import errno
import logging
from collections.abc import Callable
from functools import partial
from typing import Any, TypedDict, TypeVar

import numpy as np
from numpy.typing import NDArray

from service.bench.runtime import BenchBusy, BenchHold, BenchRuntime, DeviceNotAnswering, Hold
from service.calibration.budget import UncertaintyBudget
from service.calibration.model import CalibrationModel
from service.calibration.registry import Method, get_method
from service.errors import InputError
from service.instruments.transport import DeviceError
from service.jobs import registry
from service.jobs.active import ActiveModel, load_active, table_tilt_range_of
from service.jobs.admission import Admission
from service.jobs.bench_time import BenchTime
from service.jobs.budgets import budget_of_record
from service.jobs.events import JobEvents
from service.jobs.job_parameters import (
    JobParameters,
    OperatorPerson,
    RequestJSON,
    parameters_of,
    request_json,
)
from service.jobs.points import write_in_thread
from service.jobs.procedure import (
    JobConditions,
    JobContext,
    Outcome,
    Phase,
    PointProcedure,
    RecordValidation,
)
from service.jobs.requests import KIND_OF_PROCEDURE, CalibrationRequest, RequestProblem
from service.jobs.state import DAEMON, Ending, JobState, Stop
from service.storage.disk import DiskFull, DiskWatch, disk_full
from service.storage.engine import redacted
from service.storage.models import CalibrationJob, CalibrationRecord
from service.storage.outage import DatabaseOutage, DatabaseState, through_outage, unreachable
from service.storage.samples import Sample
from service.storage.store import Store
from service.storage.tokens import Principal

__all__ = ["ActiveModel", "JobManager", "RequestProblem"]

log = logging.getLogger("tiltlab.jobs")

LIVE = (JobState.QUEUED, JobState.RUNNING)
ENDED = (JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED)
# What a job waiting for the database shows in place of its phase (its stream and /health say so).
WAITING_FOR_DATABASE = "waiting for the database"
RANGES_KEPT = 10_000  # records whose calibrated range is remembered
DISK_RETRY_S = 2.0  # how often a job's end that found the disk full is tried again
T = TypeVar("T")


def _check_identified(bench: BenchRuntime, roles: tuple[str, ...]) -> None:
    """DeviceNotAnswering naming the first instrument a job reads that did not identify itself at
    start-up (it has no device id to store its points under)."""
    for role in roles:
        if bench.device_ids.get(role) is None:
            raise DeviceNotAnswering(
                f"{role} on {bench.port_of(role)} did not identify itself at start-up"
            )


class RecordRawData(TypedDict, total=False):
    """What a record made by a job keeps beside the job's data in its `raw_data`: the conditions,
    how many points were fitted, the uncertainty budget, the bench seconds and the operator."""

    conditions: JobConditions
    fit_points: int
    budget: UncertaintyBudget
    bench_seconds: dict[str, float]
    operator_person: OperatorPerson


def _add_operator(parameters: JobParameters, principal: Principal) -> None:
    """Who runs the job, as the token names them now (certificates state it)."""
    if principal.person is not None:
        parameters["operator_person"] = {
            "name": principal.person.name,
            "function": principal.person.function,
        }


class JobManager:
    def __init__(
        self,
        store: Store,
        benches: dict[str, BenchRuntime],
        database: DatabaseState | None = None,
        disk: DiskWatch | None = None,
        *,
        require_conditions: bool = False,
    ) -> None:
        self.store = store
        self.benches = benches
        # the free space the daemon keeps: a job does not start, and a running one stops
        # (resumable), below it
        self.disk = disk
        # job -> its end and when, not stored yet because the disk was full (written once there is
        # room)
        self.unwritten: dict[int, tuple[Stop, dt.datetime]] = {}
        # whether the database answers; a job's steps wait through an outage up to database.outage_s
        self.database = database or DatabaseState(redacted(store.engine.url))
        self.waiting_for_database: dict[int, dt.datetime] = {}  # job -> since when its step waits
        # job endings waiting for the database to come back
        self._endings: set[asyncio.Task[Any]] = set()
        self.admission = Admission(
            store.jobs, store.orders, store.standards, require_conditions=require_conditions
        )
        self.require_conditions = require_conditions
        self.tasks: dict[int, asyncio.Task[None]] = {}
        # why a job's task was cancelled from outside, and by whom
        self.stop_reasons: dict[int, Stop] = {}
        self.active: dict[str, ActiveModel | None] = {}
        # why a bench corrects nothing, when a record was withdrawn
        self.inactive_notes: dict[str, str | None] = {}
        self.events = JobEvents()  # watchers hear of every stored state, progress and point
        # Idempotency-Keys whose job is being written: a repeat waits for it, then answers that job.
        self._creating: dict[str, asyncio.Future[None]] = {}
        # record id -> its calibrated range
        self._ranges: dict[int, dict[str, list[float]] | None] = {}

    # ------------------------------------------------------------ active record per bench

    def load_active(self, bench: BenchRuntime) -> ActiveModel | None:
        """Blocking (database): the bench's active stage record, checked before use
        (`inactive_notes` says why a bench has none). Called at start-up and whenever a record is
        activated, approved or rejected."""
        loaded, note = load_active(
            self.store.records, self.store.approvals, bench, self.fit_columns, self.point_spreads
        )
        self.active[bench.name], self.inactive_notes[bench.name] = loaded, note
        return loaded

    def table_tilt_range_of(self, rec: CalibrationRecord) -> dict[str, list[float]] | None:
        """The table tilts a record was fitted on, worked out once per record (records never
        change): a page of records is read without reading each one's model and points again."""
        if rec.id in self._ranges:
            return self._ranges[rec.id]
        seen = table_tilt_range_of(rec, self.fit_columns)
        self.remember_range(rec.id, seen)
        return seen

    def known_range(self, record_id: int) -> tuple[bool, dict[str, list[float]] | None]:
        """(known, the range) of a record whose range was worked out before."""
        return (record_id in self._ranges, self._ranges.get(record_id))

    def remember_range(self, record_id: int, seen: dict[str, list[float]] | None) -> None:
        if len(self._ranges) >= RANGES_KEPT:
            self._ranges.clear()
        self._ranges[record_id] = seen

    def bench_of_device(self, device_id: int) -> BenchRuntime | None:
        return next(
            (bench for bench in self.benches.values() if device_id in bench.device_ids.values()),
            None,
        )

    # ------------------------------------------------------------ submitting

    async def submit(
        self,
        req: CalibrationRequest,
        bench: BenchRuntime,
        principal: Principal,
        idempotency_key: str | None,
    ) -> tuple[CalibrationJob, bool]:
        """A new queued job and True, or the job an earlier request with the same Idempotency-Key
        made and False."""
        self.check_disk()
        plan = await asyncio.to_thread(self.admission.plan, req, bench)
        body = request_json(req, bench.name)
        _check_identified(bench, plan.read_roles)
        device_id = bench.device_ids[plan.device_role]
        parameters = self.admission.parameters(body, bench, plan)
        _add_operator(parameters, principal)
        if bench.bench_id is None:
            raise BenchBusy(f"bench {bench.name!r} is not registered in the database yet")
        await self._same_key_written(idempotency_key)
        if bench.holder is not None:
            if idempotency_key is None:
                raise BenchBusy(f"bench {bench.name!r} is held by {bench.holder}")
            return await asyncio.to_thread(
                self.admission.replay, bench, idempotency_key, body
            ), False
        # The bench is taken before the database is: a second request while the job is being
        # written finds it busy (or, with the same key, waits for it) rather than making a second
        # job.
        bench.holder = BenchHold(Hold.JOB_BEING_CREATED)
        written: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        if idempotency_key is not None:
            self._creating[idempotency_key] = written
        try:
            job, created = await asyncio.to_thread(
                self.store.jobs.create_calibration_job,
                bench_id=bench.bench_id,
                device_id=device_id,
                kind=KIND_OF_PROCEDURE[req.procedure],
                method=req.method,
                parameters=parameters,
                actor=principal.name,
                points_total=len(plan.fit_points) + len(plan.validation_points),
                order_id=req.order_id,
                idempotency_key=idempotency_key,
                request=body if idempotency_key is not None else None,
            )
        except BaseException:
            bench.holder = None
            raise
        finally:
            if idempotency_key is not None:
                del self._creating[idempotency_key]
            written.set_result(None)
        if created:
            self._start(job.id, bench)
        else:
            bench.holder = None  # the key's earlier job, already run or running elsewhere
        return job, created

    async def _same_key_written(self, idempotency_key: str | None) -> None:
        """Wait while a first request with the same Idempotency-Key is writing its job (then the
        repeat answers that job)."""
        while idempotency_key is not None and idempotency_key in self._creating:
            # The same key's first request is writing its job: wait for it, then answer that job.
            await asyncio.shield(self._creating[idempotency_key])

    async def submit_measurement(
        self,
        bench: BenchRuntime,
        device_id: int,
        request: RequestJSON,
        points: list[list[float]],
        extra: JobParameters,
        actor: str,
    ) -> CalibrationJob:
        """A job measuring planned points (service.jobs.diagnosis_measurement) for a diagnosis: it
        holds the bench like any job (BenchBusy when another holds it) and makes no record.
        `request` says how each point is settled and read, `extra` what the job keeps of why it was
        made."""
        from service.jobs.diagnosis_measurement import NAME

        _check_identified(bench, ("reference_sensor", "measurement_sensor"))
        if bench.bench_id is None:
            raise BenchBusy(f"bench {bench.name!r} is not registered in the database yet")
        if bench.holder is not None:
            raise BenchBusy(f"bench {bench.name!r} is held by {bench.holder}")
        parameters: JobParameters = {
            **extra,
            "procedure": NAME,
            "request": request,
            "fit_points": points,
            "validation_points": [],
            "approach": "per point from the side the plan says (dir +1 from below, -1 from "
            "above) by 0.1 deg",
            "device_ids": {
                role: bench.device_ids.get(role)
                for role in ("reference_sensor", "measurement_sensor")
            },
        }
        bench.holder = BenchHold(Hold.JOB_BEING_CREATED)
        try:
            job, _ = await asyncio.to_thread(
                self.store.jobs.create_calibration_job,
                bench_id=bench.bench_id,
                device_id=device_id,
                kind="stage",
                method=str(request.get("method", "kinematic")),
                parameters=parameters,
                actor=actor,
                points_total=len(points),
                order_id=None,
                idempotency_key=None,
                request=None,
            )
        except BaseException:
            bench.holder = None
            raise
        self._start(job.id, bench)
        return job

    async def wait_for(self, job_id: int) -> CalibrationJob:
        """The job once it has ended (its task, then its stored state)."""
        task = self.tasks.get(job_id)
        if task is not None and not task.done():
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await asyncio.shield(task)
        return await asyncio.to_thread(self.store.jobs.get_job, job_id)

    def _start(self, job_id: int, bench: BenchRuntime) -> None:
        bench.holder = BenchHold.job(job_id)
        bench.stop_requested.clear()
        self.tasks[job_id] = asyncio.get_running_loop().create_task(self._run(job_id, bench))

    def check_disk(self) -> None:
        """DiskFull (507) naming the folder when the data directory has less free space than the
        daemon keeps."""
        if self.disk is not None:
            self.disk.check()

    def as_known(self, job: CalibrationJob) -> CalibrationJob:
        """The job as the daemon knows it: an end it could not store yet (a full disk) shown as it
        will be stored. The row is a detached copy; nothing is written."""
        held = self.unwritten.get(job.id)
        if held is None or job.state not in LIVE:
            return job
        stop, at = held
        job.state, job.finished_at = stop.state.value, at
        job.interrupted = stop.resumable
        job.failure_reason = f"{stop.reason} (not stored yet: written once the disk has room)"
        return job

    async def resume(self, job_id: int, principal: Principal) -> CalibrationJob:
        self.check_disk()
        # its end first: a job is resumed from what the database says of it
        if job_id in self.unwritten:
            stop, _ = self.unwritten[job_id]
            try:
                await write_in_thread(self._end_job, job_id, stop)
            except Exception as exc:
                if not disk_full(exc):
                    raise
                raise DiskFull(errno.ENOSPC, self._disk_reason(exc)) from None
            self.unwritten.pop(job_id, None)
        job = await asyncio.to_thread(self.store.jobs.get_job, job_id)
        bench = next(
            (
                candidate
                for candidate in self.benches.values()
                if candidate.bench_id == job.bench_id
            ),
            None,
        )
        if bench is None:
            raise RequestProblem(
                "id", f"job {job_id} ran on a bench this daemon does not run", status=409
            )
        if bench.holder is not None:
            raise BenchBusy(f"bench {bench.name!r} is held by {bench.holder}")
        bench.holder = BenchHold(Hold.JOB_RESUMING, job_id)
        try:
            job = await asyncio.to_thread(self.store.jobs.resume_job, job_id, actor=principal.name)
        except BaseException:
            bench.holder = None
            raise
        self._start(job_id, bench)
        return job

    # ------------------------------------------------------------ ending from outside

    async def cancel(self, job_id: int, principal: Principal) -> CalibrationJob:
        job = await asyncio.to_thread(self.store.jobs.get_job, job_id)
        if job.state not in LIVE:
            raise RequestProblem(
                "id",
                f"job {job_id} is {job.state}; only a queued or running job can be cancelled",
                status=409,
            )
        await self._end_task(
            job_id, Stop(Ending.CANCELLED, f"cancelled by {principal.name}", actor=principal.name)
        )
        return await asyncio.to_thread(self.store.jobs.get_job, job_id)

    async def stop_bench(self, bench: BenchRuntime, principal: Principal) -> int | None:
        """Stop motion now; a running job fails with the reason. Returns the failed job's id."""
        # The job is named before the stop: once the axes stand, the job may end by itself (its move
        # fails) and let go of the bench before this coroutine runs again.
        job_id = next(
            (j for j, t in self.tasks.items() if bench.holder == BenchHold.job(j) and not t.done()),
            None,
        )
        stop = Stop(
            Ending.FAILED,
            f"stopped by POST /stage/stop ({principal.name}) while the job ran",
            actor=principal.name,
        )
        if job_id is not None:
            self.stop_reasons[job_id] = stop  # the job's own failure, if first, says why
        await bench.stop()
        if job_id is not None:
            await self._end_task(job_id, stop)
            # again: a move the job had half sent (one axis) before it ended is stopped too
            await bench.stop()
        return job_id

    async def _end_task(self, job_id: int, stop: Stop) -> None:
        task = self.tasks.get(job_id)
        if task is not None and not task.done():
            self.stop_reasons[job_id] = stop
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        else:
            job = await asyncio.to_thread(self.store.jobs.get_job, job_id)
            if job.state in LIVE:
                await self._finish(job_id, stop)

    async def _finish(self, job_id: int, stop: Stop) -> None:
        """The job's end written; while the database is away it is written when the database answers
        again (however long that takes), and the caller (a stop, a cancel, the job's task) goes
        on."""
        try:
            await write_in_thread(self._end_job, job_id, stop)
        except Exception as exc:
            if disk_full(exc):  # known here, shown as ended, stored once the disk has room
                log.warning(
                    "job %s: its end (%s) cannot be stored, the disk is full; it is written "
                    "once there is room",
                    job_id,
                    stop.reason,
                )
                self.unwritten[job_id] = (stop, dt.datetime.now(dt.UTC))
                ending = asyncio.get_running_loop().create_task(self._store_when_room(job_id, stop))
                self._endings.add(ending)
                ending.add_done_callback(partial(self._ended_later, job_id))
                self.events.changed(job_id)
                return
            if not unreachable(exc):
                raise
            if not isinstance(exc, DatabaseOutage):
                self.database.away(exc)
            log.warning(
                "job %s: its end (%s) is written once the database answers again",
                job_id,
                stop.reason,
            )
            ending = asyncio.get_running_loop().create_task(
                through_outage(
                    self.database,
                    partial(write_in_thread, self._end_job, job_id, stop),
                    give_up=False,
                )
            )
            self._endings.add(ending)
            ending.add_done_callback(partial(self._ended_later, job_id))
        self.events.changed(job_id)

    async def _store_when_room(self, job_id: int, stop: Stop) -> None:
        """Try to store a job's end again every DISK_RETRY_S until the disk has room (or a resume
        stored it)."""
        while job_id in self.unwritten:
            await asyncio.sleep(DISK_RETRY_S)
            if job_id not in self.unwritten:
                return
            try:
                await write_in_thread(self._end_job, job_id, stop)
            except Exception as exc:
                if disk_full(exc) or unreachable(exc):
                    continue
                raise
            self.unwritten.pop(job_id, None)
            log.warning("job %s: its end is stored now (%s)", job_id, stop.reason)

    def _disk_reason(self, exc: BaseException) -> str:
        return self.disk.described(exc) if self.disk is not None else f"disk full: {exc}"

    def _ended_later(self, job_id: int, task: asyncio.Task[Any]) -> None:
        self._endings.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("job %s: its end could not be written: %s", job_id, task.exception())
        self.events.changed(job_id)

    async def _db(self, job_id: int, call: Callable[..., T], /, *args: Any, **kwargs: Any) -> T:
        """A job's database step in a worker thread, waiting through an outage (the job shows it
        waits) until the outage outlasts TILTLAB_DB_OUTAGE_S (then DatabaseOutage). `call` must be
        safe to repeat."""
        # before every step: a job stops with room left to store why, not on a full disk
        self.check_disk()
        held = sum(
            len(arg) for arg in args if isinstance(arg, list) and arg and isinstance(arg[0], Sample)
        )
        return await through_outage(
            self.database,
            partial(write_in_thread, call, *args, **kwargs),
            on_wait=partial(self._waiting, job_id),
            samples=held,
        )

    def _waiting(self, job_id: int, waits: bool) -> None:
        if waits:
            self.waiting_for_database[job_id] = dt.datetime.now(dt.UTC)
            log.warning("job %s: %s", job_id, WAITING_FOR_DATABASE)
        else:
            self.waiting_for_database.pop(job_id, None)
        self.events.changed(job_id)

    def _end_job(self, job_id: int, stop: Stop) -> None:
        """Blocking (database): the job cancelled or failed, audited with whoever ended it. Safe to
        repeat: a job already ended (an earlier try whose answer was lost) is left as it is."""
        job = self.store.jobs.get_job(job_id)
        if job.state in ENDED:
            return
        if job.state == JobState.QUEUED and stop.ending is not Ending.CANCELLED:
            self.store.jobs.start_job(job_id, actor=DAEMON)
        if stop.ending is Ending.CANCELLED:
            self.store.jobs.cancel_job(job_id, actor=stop.actor, reason=stop.reason)
        elif stop.resumable:
            self.store.jobs.interrupt_job(job_id, stop.reason, actor=stop.actor)
        else:
            self.store.jobs.fail_job(job_id, stop.reason, actor=stop.actor)

    async def shutdown(self) -> None:
        """Daemon stopping: running jobs are left as interrupted (resumable), not failed for
        good."""
        for job_id, task in list(self.tasks.items()):
            if not task.done():
                self.stop_reasons[job_id] = Stop(Ending.INTERRUPTED, "the daemon stopped")
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
        # the database is away: the next start marks these jobs interrupted
        for ending in list(self._endings):
            ending.cancel()
        try:
            # this daemon's benches only
            await write_in_thread(
                self.store.jobs.mark_interrupted,
                actor=DAEMON,
                bench_ids=[
                    bench.bench_id for bench in self.benches.values() if bench.bench_id is not None
                ],
            )
        except Exception as exc:
            if not unreachable(exc):
                raise
            log.warning(
                "the database is away: jobs left running are marked interrupted at the next start"
            )

    # ------------------------------------------------------------ running

    async def _report(
        self,
        job_id: int,
        points_done: int,
        points_total: int,
        phase: Phase,
        bench_time: BenchTime | None = None,
    ) -> None:
        await self._db(
            job_id,
            self.store.jobs.set_job_progress,
            job_id,
            points_done=points_done,
            points_total=points_total,
            phase=phase,
            bench_seconds=bench_time.as_json() if bench_time is not None else None,
        )
        self.events.changed(job_id)

    def _start_job(self, job_id: int) -> CalibrationJob:
        """Blocking (database): the job running. Safe to repeat (a job already running is left
        so)."""
        job = self.store.jobs.get_job(job_id)
        return (
            self.store.jobs.start_job(job_id, actor=DAEMON) if job.state == JobState.QUEUED else job
        )

    async def _run(self, job_id: int, bench: BenchRuntime) -> None:
        try:
            job = await self._db(job_id, self.store.jobs.get_job, job_id)
            if job.state == JobState.QUEUED:
                await self._db(job_id, self._start_job, job_id)
                self.events.changed(job_id)
            procedure = registry.procedure_of(parameters_of(job))
            request = CalibrationRequest.model_validate(parameters_of(job)["request"])

            bench_time = BenchTime.from_json(job.bench_seconds)  # a resumed job goes on counting

            async def report(points_done: int, points_total: int, phase: Phase) -> None:
                await self._report(job_id, points_done, points_total, phase, bench_time)

            outcome = await procedure.run(
                JobContext(
                    self.store, job, bench, request, report, partial(self._db, job_id), bench_time
                )
            )
            await self._db(job_id, self._conclude, job, outcome)
        except asyncio.CancelledError:
            stop = self.stop_reasons.pop(
                job_id, Stop(Ending.FAILED, "the job's task was cancelled")
            )
            if stop.ending is not Ending.INTERRUPTED:
                with contextlib.suppress(Exception):
                    await self._finish(job_id, stop)
        except Exception as exc:  # noqa: BLE001 - a job must never be left running
            stop = self._ending_of(job_id, bench, exc)
            if stop.ending is not Ending.INTERRUPTED:
                with contextlib.suppress(Exception):
                    await self._finish(job_id, stop)
        finally:
            self.stop_reasons.pop(job_id, None)
            self.waiting_for_database.pop(job_id, None)
            if bench.holder == BenchHold.job(job_id):
                bench.holder = None
            self.events.changed(job_id)

    def _ending_of(self, job_id: int, bench: BenchRuntime, exc: Exception) -> Stop:
        """How a job whose task failed ends. A stop by request that the job saw first says why (a
        daemon stopping leaves the job interrupted, to be resumed); a full disk stops it resumable;
        a database outage that outlasted TILTLAB_DB_OUTAGE_S, an instrument or a bad input fail it
        naming them; anything else is an internal error."""
        stopped = self.stop_reasons.pop(job_id, None)
        if disk_full(exc):  # (or below the room the daemon keeps)
            reason = (
                f"{self._disk_reason(exc)}; nothing more was measured. Free space, then"
                f" POST /calibrations/{job_id}/resume continues the job from its stored points"
            )
            log.warning("job %s stopped: %s", job_id, reason)
            return stopped if stopped is not None else Stop(Ending.FAILED, reason, resumable=True)
        if isinstance(exc, DatabaseOutage):
            log.warning("job %s failed: %s", job_id, exc)
            return stopped if stopped is not None else Stop(Ending.FAILED, str(exc))
        if isinstance(exc, DeviceError | DeviceNotAnswering | TimeoutError | InputError):
            log.warning("job %s failed: %s", job_id, exc)
            return stopped if stopped is not None else Stop(Ending.FAILED, self._reason(bench, exc))
        log.error("job %s failed", job_id, exc_info=exc)
        return Stop(Ending.FAILED, f"internal error: {type(exc).__name__}: {exc}")

    @staticmethod
    def _reason(bench: BenchRuntime, exc: Exception) -> str:
        text = str(exc)
        down = [status for status in bench.devices.status() if status.state != "connected"]
        if down:
            text += "; not answering: " + ", ".join(
                f"{status.role} on {status.port} ({status.state})" for status in down
            )
        return text

    def _conclude(self, job: CalibrationJob, outcome: Outcome) -> None:
        """Blocking (database): the record version, then the job succeeded. Safe to repeat: a job
        makes one record, so a record already stored for it (an earlier try whose answer was lost)
        is not made again."""
        if outcome.model is None or job.id in self.store.records.records_of_jobs([job.id]):
            # a measurement that makes no record, or a record already stored for the job
            if self.store.jobs.get_job(job.id).state != JobState.SUCCEEDED:
                self.store.jobs.succeed_job(job.id, actor=DAEMON)
            return
        ids = parameters_of(job)["request"].get("reference_standards") or []
        standards = self.admission.standards(ids)
        method = get_method(outcome.kind, job.method)
        fit_cols = self._budget_columns(job, outcome)
        self._check_conditions_recorded(outcome)
        budget = budget_of_record(
            method,
            outcome.model,
            fit_cols,
            standards,
            outcome.conditions.get("resolution_deg") or {},
        )
        raw: RecordRawData = {
            "conditions": outcome.conditions,
            "fit_points": outcome.n_fit,
            "budget": budget,
        }
        if outcome.bench_seconds is not None:
            raw["bench_seconds"] = outcome.bench_seconds
            self.store.jobs.set_bench_seconds(job.id, outcome.bench_seconds)
        if operator := parameters_of(job).get("operator_person"):
            raw["operator_person"] = operator
        self.store.records.add_record(
            outcome.device_id,
            outcome.kind,
            job.method,
            outcome.model.to_json_dict(),
            operator=job.created_by,
            validation=outcome.validation,
            temp_c=outcome.conditions["temp_c_mean"],
            job_id=job.id,
            reference_standards=standards,
            raw_data=raw,
        )
        self.store.jobs.succeed_job(job.id, actor=DAEMON)

    def _budget_columns(
        self, job: CalibrationJob, outcome: Outcome
    ) -> dict[str, NDArray[np.float64]] | None:
        """Blocking (database): the fit columns a stage record's budget judges the corrected tilt
        on (None for other kinds, whose budget has no such entries)."""
        procedure = registry.procedure_of(parameters_of(job))
        if outcome.kind == "stage" and isinstance(procedure, PointProcedure):
            return procedure.stored_columns(self.store.points, job, outcome.n_fit)
        return None

    def _check_conditions_recorded(self, outcome: Outcome) -> None:
        """Where the laboratory requires conditions, a job that recorded no ambient temperature
        makes no record."""
        if self.require_conditions and not outcome.conditions.get("ambient_temperature_c"):
            raise InputError(
                "the laboratory requires the ambient conditions of every calibration, and none "
                "was recorded: the bench's ambient sensor gave no reading during the job and "
                "the request gave no conditions.ambient_temperature_c"
            )

    # ------------------------------------------------------------ a finished job's points

    def point_spreads(
        self, job_id: int, device_id: int
    ) -> list[tuple[int, float | None, float | None]]:
        """Blocking (database): (readings, sd x, sd y) of each point a device settled in a job."""
        return [
            (settled_point.n_samples, settled_point.ch_x_std, settled_point.ch_y_std)
            for settled_point in self.store.points.settled_points(job_id, device_id)
        ]

    def fit_columns(self, job_id: int, n_fit: int) -> dict[str, NDArray[np.float64]]:
        """Blocking (database): the dataset columns of a job's first `n_fit` settled points."""
        job = self.store.jobs.get_job(job_id)
        procedure = registry.procedure_of(parameters_of(job))
        if not isinstance(procedure, PointProcedure):
            raise InputError(f"job {job_id} ({procedure.name}) measured no points")
        return procedure.stored_columns(self.store.points, job, n_fit)

    def validate(
        self, job_id: int, n_fit: int, method: Method, model: CalibrationModel
    ) -> RecordValidation:
        """Blocking (database): a model against the job's points from `n_fit` on (its validation
        points)."""
        job = self.store.jobs.get_job(job_id)
        procedure = registry.procedure_of(parameters_of(job))
        if not isinstance(procedure, PointProcedure):
            raise InputError(f"job {job_id} ({procedure.name}) measured no points")
        points = [
            settled_point
            for settled_point in self.store.points.settled_points(job_id)
            if settled_point.point >= n_fit
        ]
        return procedure.validation(method, model, procedure.columns(job, points, for_fit=False))
