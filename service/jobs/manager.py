"""Jobs on the daemon's benches: one per bench, every step persisted, interruptible and resumable.

A stage-grid job approaches every point from below on both axes (backlash taken up on one side),
waits until both sensors settle, averages `samples_per_point` readings of each after the stated
outlier rule, stores the raw samples and the per-point means as it goes, fits with the method of
`tiltlab calibrate`, measures validation points not used in the fit, and appends a record version.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from service import __version__
from service.bench.readings import OUTLIER_RULE, fresh_readings, robust_mean, settle
from service.bench.runtime import BenchBusy, BenchRuntime, DeviceNotAnswering, StageNotHomed
from service.calibration.model import CalibrationModel, stored_table_tilt_range, table_tilt_range
from service.calibration.registry import FitOptions, get_method
from service.calibration.uncertainty import COVERAGE
from service.errors import InputError
from service.instruments.transport import DeviceError
from service.jobs import angles
from service.jobs.budgets import budget_of_record, resolutions_deg
from service.jobs.events import JobEvents
from service.jobs.points import store_point, write_in_thread
from service.jobs.requests import KIND_OF_PROCEDURE, MIN_POINTS, CalibrationRequest
from service.storage.daemon_jobs import DaemonStore
from service.storage.errors import ConflictError, UnknownEntity
from service.storage.lims import StandardNotUsable
from service.storage.samples import Sample
from service.storage.tokens import Principal

log = logging.getLogger("tiltlab.jobs")

APPROACH_DEG = 0.1  # every point is approached from this far below on both axes
SENSORS = ("reference_sensor", "measurement_sensor")



def _tilt(value: float | None) -> float:
    """A sensor reading's angle; an inclinometer reading always has both."""
    if value is None:
        raise DeviceError("an inclinometer reading came without its angle")
    return value

class RequestProblem(InputError):
    """A request that cannot be used; `field` names what was wrong."""

    def __init__(self, field: str, message: str, status: int = 422) -> None:
        super().__init__(f"{field}: {message}")
        self.field, self.status = field, status


@dataclass
class ActiveModel:
    record_id: int
    version: int
    method_name: str
    model: CalibrationModel
    method: Any
    budget: dict[str, Any] | None = None  # the record's uncertainty budget (what adds to the fit's part)
    status: str = "draft"  # draft | approved (a rejected record is never loaded)
    # the table tilts (reference sensor's frame) the record was fitted on: {"x": [min, max], "y": [min, max]}
    table_tilt_range_deg: dict[str, list[float]] | None = None


def stage_columns(points_ref, points_meas) -> dict[str, np.ndarray]:  # type: ignore[no-untyped-def]
    """The dataset columns of a job's settled points (reference and measurement rows by point)."""
    meas = {p.point: p for p in points_meas}
    rows = [(r, meas[r.point]) for r in points_ref if r.point in meas]
    col = lambda f: np.array([f(r, m) for r, m in rows], dtype=float)  # noqa: E731
    return {
        "point": col(lambda r, m: r.point),
        "stage_x_deg": col(lambda r, m: r.cmd_x_deg), "stage_y_deg": col(lambda r, m: r.cmd_y_deg),
        "dir_x": col(lambda r, m: 1.0), "dir_y": col(lambda r, m: 1.0),
        "ref_x_deg": col(lambda r, m: r.ch_x_mean), "ref_y_deg": col(lambda r, m: r.ch_y_mean),
        "meas_x_deg": col(lambda r, m: m.ch_x_mean), "meas_y_deg": col(lambda r, m: m.ch_y_mean),
        "temp_c": col(lambda r, m: m.temp_c_mean if m.temp_c_mean is not None else np.nan),
        "t_s": col(lambda r, m: r.t_end_s),
    }


def job_conditions(bench: BenchRuntime, req: dict, temps_c: list[float]) -> dict[str, Any]:
    """What a record keeps of the conditions it was measured under."""
    return {"temp_c_mean": float(np.mean(temps_c)) if len(temps_c) else None, "software_version": __version__,
            "firmware": {r: (i.firmware if i else None) for r, i in bench.identities.items()},
            "instruments": {r: (f"{i.model} s/n {i.serial}" if i else None) for r, i in bench.identities.items()},
            "resolution_deg": resolutions_deg(bench),
            "bench": bench.name, "clock_speed": bench.clock.speed, "outlier_rule": OUTLIER_RULE,
            "samples_per_point": req["samples_per_point"], "settle": req["settle"]}


class JobManager:
    def __init__(self, store: DaemonStore, benches: dict[str, BenchRuntime]) -> None:
        self.store = store
        self.benches = benches
        self.tasks: dict[int, asyncio.Task] = {}
        self.stop_reasons: dict[int, str] = {}
        self.active: dict[str, ActiveModel | None] = {}
        self.inactive_notes: dict[str, str | None] = {}  # why a bench corrects nothing, when a record was withdrawn
        self.events = JobEvents()  # watchers hear of every stored state, progress and point

    # ------------------------------------------------------------ active record per bench

    def load_active(self, bench: BenchRuntime) -> ActiveModel | None:
        """The bench's active stage record, checked before use: a record whose stored content no longer
        matches its hash is refused (the bench stays uncorrected, `inactive_notes` says why), and a rejected
        one is withdrawn. Called at start-up and whenever a record is activated, approved or rejected."""
        dev = bench.device_ids.get("measurement_sensor")
        rec = self.store.active_record(dev, "stage") if dev is not None else None
        loaded, note = None, None
        if rec is None:
            note = self.store.inactive_reason(dev, "stage") if dev is not None else None
        elif (why := self.store.unusable_reason(rec.id)) is not None:
            note = f"the active record is refused: {why}"
            log.warning("bench %s: %s", bench.name, note)
            if self.store.record_status(rec.id) == "rejected" and dev is not None:
                with contextlib.suppress(ConflictError):  # a rejected record is never used: withdraw it
                    self.store.deactivate(dev, "stage", actor="daemon", replaces=rec.id,
                                          reason=f"{why}; a rejected record is never used")
        else:
            model = CalibrationModel.from_json_dict(rec.model, f"record {rec.id}")
            loaded = ActiveModel(rec.id, rec.version, rec.method, model, get_method("stage", rec.method),
                                 (rec.raw_data or {}).get("budget"), status=self.store.record_status(rec.id),
                                 table_tilt_range_deg=self.table_tilt_range_of(rec, model))
        self.active[bench.name], self.inactive_notes[bench.name] = loaded, note
        return loaded

    def table_tilt_range_of(self, rec: Any, model: CalibrationModel | None = None) -> dict[str, list[float]] | None:
        """The table tilts a stage record was fitted on: from its model, else (records made before models
        kept it) from the settled points its job fitted; None for other kinds or without either."""
        if rec.kind != "stage":
            return None
        model = model or CalibrationModel.from_json_dict(rec.model, f"record {rec.id}")
        seen = stored_table_tilt_range(model)
        if seen is None and rec.job_id is not None:
            with contextlib.suppress(UnknownEntity, KeyError):
                seen = table_tilt_range(self.fit_columns(rec.job_id, None, int((rec.raw_data or {}).get("fit_points", 10**9))))
        return seen

    def bench_of_device(self, device_id: int) -> BenchRuntime | None:
        return next((b for b in self.benches.values() if device_id in b.device_ids.values()), None)

    # ------------------------------------------------------------ submitting

    def check(self, req: CalibrationRequest, bench: BenchRuntime) -> tuple[list, list]:
        """Fit and validation points of a request; RequestProblem names the field that cannot be used."""
        self.check_traceability(req)
        if req.procedure in angles.PROCEDURES:
            return self._check_angles(req, bench, angles.PROCEDURES[req.procedure])
        if req.procedure != "stage-grid":
            raise RequestProblem("procedure", f"{req.procedure!r} jobs are not run by this daemon version; "
                                 "it runs stage-grid, scale, rotation and turntable jobs")
        if bench.kind != "stage":
            raise RequestProblem("bench", f"{bench.name!r} is a {bench.kind} bench; stage-grid needs a stage bench")
        try:
            get_method("stage", req.method)
        except InputError as exc:
            raise RequestProblem("method", str(exc)) from None
        if req.grid is None:
            raise RequestProblem("grid", "a stage-grid job needs a grid")
        points = req.grid.stage_points()
        travel = bench.config.stage_bench().travel_deg
        for i, (x, y) in enumerate(points):
            if abs(x) > travel or abs(y) > travel:
                field = "grid.points" if req.grid.points is not None else "grid.x_deg" if abs(x) > travel else "grid.y_deg"
                raise RequestProblem(field, f"point {i} ({x:g}, {y:g}) deg is outside the stage travel of ±{travel:g} deg")
        need = MIN_POINTS.get(req.method, 6)
        if len(points) < need:
            raise RequestProblem("grid", f"{len(points)} points; {req.method} needs at least {need}")
        xs, ys = np.array(points).T
        rng = np.random.default_rng(len(points) * 7919 + req.validation.n_points)
        val = [(float(round(x, 4)), float(round(y, 4))) for x, y in zip(
            rng.uniform(xs.min(), xs.max(), req.validation.n_points),
            rng.uniform(ys.min(), ys.max(), req.validation.n_points))]
        return points, val

    def check_traceability(self, req: CalibrationRequest) -> None:
        """Every reference standard the job names is registered and not past its due date; the order exists."""
        try:
            self.store.usable_standards(req.reference_standards, on=dt.datetime.now(dt.UTC).date())
        except StandardNotUsable as exc:
            raise RequestProblem(exc.field, exc.reason) from None
        if req.order_id is not None:
            try:
                self.store.order(req.order_id)
            except UnknownEntity:
                raise RequestProblem("order_id", f"there is no order {req.order_id} (POST /orders)") from None

    def _check_angles(self, req: CalibrationRequest, bench: BenchRuntime, proc: angles.AngleProcedure):  # type: ignore[no-untyped-def]
        if bench.kind != proc.bench_kind:
            raise RequestProblem("bench", f"{bench.name!r} is a {bench.kind} bench; {proc.name} needs a "
                                 f"{proc.bench_kind} bench")
        for role in proc.read_roles:
            if role not in bench.devices:
                raise RequestProblem("bench", f"{bench.name!r} has no {role}; {proc.name} needs it")
        try:
            get_method(proc.kind, req.method)
        except InputError as exc:
            raise RequestProblem("method", str(exc)) from None
        if req.grid is None or not req.grid.is_angles():
            raise RequestProblem("grid", f"a {proc.name} job needs angles: grid.angles_deg, or grid.range_deg and grid.n")
        pts = req.grid.angles()
        lo, hi = proc.travel(bench)
        for i, a in enumerate(pts):
            if not lo <= a <= hi:
                raise RequestProblem("grid.angles_deg" if req.grid.angles_deg is not None else "grid.range_deg",
                                     f"angle {i} ({a:g} deg) is outside [{lo:g}, {hi:g}] deg")
        need = proc.min_points
        if proc.name == "scale" and req.method.startswith("poly") and req.method[4:].isdigit():
            need = int(req.method[4:]) + 2
        distinct = len({a % 180.0 for a in pts}) if proc is angles.TURNTABLE else len(set(pts))
        if distinct < need:
            raise RequestProblem("grid", f"{distinct} distinct angles{' (modulo 180 deg)' if proc is angles.TURNTABLE else ''};"
                                 f" {req.method} needs at least {need}")
        rng = np.random.default_rng(len(pts) * 7919 + req.validation.n_points)
        val = [float(round(a, 4)) for a in rng.uniform(min(pts), max(pts), req.validation.n_points)]
        if proc is angles.TURNTABLE:
            if req.reference is None:
                raise RequestProblem("reference", "a turntable job needs the axis reference: "
                                     '{"north_arcsec": ..., "east_arcsec": ...}')
            return [x for a in pts for x in (a, a + 180.0)], [x for a in val for x in (a, a + 180.0)]
        return pts, val

    def _standards(self, req: dict) -> list[dict]:
        """The registered standards a job named, as its record keeps them (traceability of the result)."""
        return [{"id": st.id, "name": st.name, "serial": st.serial, "certificate_id": st.certificate_number,
                 "certificate_sha256": st.certificate_sha256, "expanded_uncertainty_deg": st.expanded_uncertainty_deg,
                 "coverage_factor": st.coverage_factor}
                for st in map(self.store.standard, req.get("reference_standards") or [])]

    async def submit(self, req: CalibrationRequest, bench: BenchRuntime, principal: Principal,
                     idempotency_key: str | None):  # type: ignore[no-untyped-def]
        points, val = await asyncio.to_thread(self.check, req, bench)
        body = req.model_dump(mode="json")
        body["bench"] = bench.name
        proc = angles.PROCEDURES.get(req.procedure)
        role = proc.device_role if proc else "measurement_sensor"
        roles = proc.read_roles if proc else SENSORS
        for r in roles:
            if bench.device_ids.get(r) is None:
                raise DeviceNotAnswering(f"{r} on {bench.port_of(r)} did not identify itself at start-up")
        dev = bench.device_ids[role]
        kind = KIND_OF_PROCEDURE[req.procedure]
        parameters = {"request": body, "fit_points": points, "validation_points": val, "outlier_rule": OUTLIER_RULE,
                      "approach": f"from below on both axes by {APPROACH_DEG} deg",
                      "device_ids": {r: bench.device_ids.get(r) for r in roles}}
        if bench.bench_id is None:
            raise BenchBusy(f"bench {bench.name!r} is not registered in the database yet")
        if bench.holder is not None:
            if idempotency_key is None:
                raise BenchBusy(f"bench {bench.name!r} is held by {bench.holder}")
            return await asyncio.to_thread(self._replay_or_busy, bench, idempotency_key, body)
        # The bench is taken before the database is: a second request while the job is being
        # written finds it busy rather than making a second job.
        bench.holder = "a job being created"
        try:
            job, created = await asyncio.to_thread(
                self.store.create_calibration_job, bench_id=bench.bench_id, device_id=dev, kind=kind,
                method=req.method, parameters=parameters, actor=principal.name,
                points_total=len(points) + len(val), order_id=req.order_id, idempotency_key=idempotency_key,
                request=body if idempotency_key is not None else None)
        except BaseException:
            bench.holder = None
            raise
        if created:
            self._start(job.id, bench)
        else:
            bench.holder = None  # the key's earlier job, already run or running elsewhere
        return job, created

    def _replay_or_busy(self, bench: BenchRuntime, key: str, body: dict):  # type: ignore[no-untyped-def]
        """A busy bench still answers a repeated request with its job; anything else is 409."""
        import sqlalchemy as sa

        from service.storage.canonical import sha256_hex
        from service.storage.daemon_jobs import IdempotencyMismatch
        from service.storage.models import IdempotencyKey

        with self.store.session() as s:
            seen = s.scalar(sa.select(IdempotencyKey).where(IdempotencyKey.route == "calibrations",
                                                             IdempotencyKey.key == key))
        if seen is None:
            raise BenchBusy(f"bench {bench.name!r} is held by {bench.holder}")
        if seen.request_sha256 != sha256_hex(body):
            raise IdempotencyMismatch(f"Idempotency-Key {key!r} was used for another request body (job {seen.job_id});"
                                      " use a new key for a new request")
        if seen.job_id is None:
            raise IdempotencyMismatch(f"Idempotency-Key {key!r} belongs to a request that made no job")
        return self.store.get_job(seen.job_id), False

    def _start(self, job_id: int, bench: BenchRuntime, resume: bool = False) -> None:
        bench.holder = f"job {job_id}"
        bench.stop_requested.clear()
        task = asyncio.get_running_loop().create_task(self._run(job_id, bench, resume))
        self.tasks[job_id] = task

    async def resume(self, job_id: int, principal: Principal):  # type: ignore[no-untyped-def]
        job = await asyncio.to_thread(self.store.get_job, job_id)
        bench = next((b for b in self.benches.values() if b.bench_id == job.bench_id), None)
        if bench is None:
            raise RequestProblem("id", f"job {job_id} ran on a bench this daemon does not run", status=409)
        if bench.holder is not None:
            raise BenchBusy(f"bench {bench.name!r} is held by {bench.holder}")
        bench.holder = f"job {job_id} (resuming)"
        try:
            job = await asyncio.to_thread(self.store.resume_job, job_id, actor=principal.name)
        except BaseException:
            bench.holder = None
            raise
        self._start(job_id, bench, resume=True)
        return job

    async def cancel(self, job_id: int, principal: Principal):  # type: ignore[no-untyped-def]
        job = await asyncio.to_thread(self.store.get_job, job_id)
        if job.state not in ("queued", "running"):
            raise RequestProblem("id", f"job {job_id} is {job.state}; only a queued or running job can be cancelled",
                                 status=409)
        await self._end_task(job_id, f"cancelled by {principal.name}", state="cancelled")
        return await asyncio.to_thread(self.store.get_job, job_id)

    async def stop_bench(self, bench: BenchRuntime, principal: Principal) -> int | None:
        """Stop motion now; a running job fails with the reason. Returns the failed job's id."""
        # The job is named before the stop: once the axes stand, the job may end by itself (its move
        # fails) and let go of the bench before this coroutine runs again.
        job_id = next((j for j, t in self.tasks.items() if bench.holder == f"job {j}" and not t.done()), None)
        reason = f"stopped by POST /stage/stop ({principal.name}) while the job ran"
        if job_id is not None:
            self.stop_reasons[job_id] = f"failed:{reason}"  # the job's own failure, if first, says why
        await bench.stop()
        if job_id is not None:
            await self._end_task(job_id, reason, state="failed")
            await bench.stop()  # again: a move the job had half sent (one axis) before it ended is stopped too
        return job_id

    async def _end_task(self, job_id: int, reason: str, state: str) -> None:
        task = self.tasks.get(job_id)
        if task is not None and not task.done():
            self.stop_reasons[job_id] = f"{state}:{reason}"
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        else:
            job = await asyncio.to_thread(self.store.get_job, job_id)
            if job.state in ("queued", "running"):
                await self._finish(job_id, state, reason)

    async def _finish(self, job_id: int, state: str, reason: str) -> None:
        await write_in_thread(self._end_job, job_id, state, reason)
        self.events.changed(job_id)

    def _end_job(self, job_id: int, state: str, reason: str) -> None:
        job = self.store.get_job(job_id)
        if job.state == "queued" and state != "cancelled":
            self.store.start_job(job_id, actor="daemon")
        if state == "cancelled":
            self.store.cancel_job(job_id, actor="daemon", reason=reason)
        else:
            self.store.fail_job(job_id, reason, actor="daemon")

    async def _progress(self, job_id: int, *, points_done: int, points_total: int, phase: str) -> None:
        await write_in_thread(self.store.set_job_progress, job_id, points_done=points_done,
                              points_total=points_total, phase=phase)
        self.events.changed(job_id)

    async def shutdown(self) -> None:
        """Daemon stopping: running jobs are left as interrupted (resumable), not failed for good."""
        for job_id, task in list(self.tasks.items()):
            if not task.done():
                self.stop_reasons[job_id] = "shutdown:"
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
        await write_in_thread(self.store.mark_interrupted, actor="daemon")

    # ------------------------------------------------------------ running

    async def _run(self, job_id: int, bench: BenchRuntime, resume: bool) -> None:
        try:
            job = await asyncio.to_thread(self.store.get_job, job_id)
            if job.state == "queued":
                await write_in_thread(self.store.start_job, job_id, actor="daemon")
                self.events.changed(job_id)
            if job.parameters["request"]["procedure"] in angles.PROCEDURES:
                await self._angle_job(job_id, bench, angles.PROCEDURES[job.parameters["request"]["procedure"]])
            else:
                await self._stage_grid(job_id, bench)
        except asyncio.CancelledError:
            why = self.stop_reasons.pop(job_id, "failed:the job's task was cancelled")
            state, _, reason = why.partition(":")
            if state != "shutdown":
                with contextlib.suppress(Exception):
                    await self._finish(job_id, state, reason)
        except (DeviceError, DeviceNotAnswering, TimeoutError, InputError) as exc:
            log.warning("job %s failed: %s", job_id, exc)
            stopped = self.stop_reasons.pop(job_id, None)  # a stop by request that the job saw first
            state, _, reason = (stopped or "").partition(":")
            if state != "shutdown":  # (a daemon stopping leaves the job interrupted, to be resumed)
                with contextlib.suppress(Exception):
                    await self._finish(job_id, state or "failed", reason or self._reason(bench, exc))
        except Exception as exc:  # noqa: BLE001 - a job must never be left running
            log.exception("job %s failed", job_id)
            with contextlib.suppress(Exception):
                await self._finish(job_id, "failed", f"internal error: {type(exc).__name__}: {exc}")
        finally:
            self.stop_reasons.pop(job_id, None)
            if bench.holder == f"job {job_id}":
                bench.holder = None
            self.events.changed(job_id)

    @staticmethod
    def _reason(bench: BenchRuntime, exc: Exception) -> str:
        text = str(exc)
        down = [s for s in bench.devices.status() if s.state != "connected"]
        if down:
            text += "; not answering: " + ", ".join(f"{s.role} on {s.port} ({s.state})" for s in down)
        return text

    async def _measure_point(self, job_id: int, bench: BenchRuntime, index: int, x: float, y: float,
                             req: dict) -> None:
        travel = bench.config.stage_bench().travel_deg
        approach = (max(x - APPROACH_DEG, -travel), max(y - APPROACH_DEG, -travel))
        try:
            await bench.move_stage(*approach)
        except StageNotHomed:
            await self._home_stage(job_id, bench)
            await bench.move_stage(*approach)
        cx, cy = await bench.move_stage(x, y)
        st = req["settle"]
        t0 = await settle(bench, SENSORS, tolerance_deg=st["tolerance_deg"], window_s=st["window_s"],
                          timeout_s=st["timeout_s"])
        n = req["samples_per_point"]
        timeout = max(5.0, 20 * n * max(bench.output_interval_s(r) for r in SENSORS))
        ref, meas = await asyncio.gather(*(fresh_readings(bench, r, n, after_bench_s=t0, timeout_s=timeout)
                                           for r in SENSORS))
        epoch = bench.clock.utc().timestamp() - bench.clock.real_seconds(bench.clock.monotonic())
        to_epoch = lambda bs: epoch + bench.clock.real_seconds(bs)  # noqa: E731
        rows, settled = [], {}
        for role, readings in (("reference_sensor", ref), ("measurement_sensor", meas)):
            dev = bench.device_ids[role]
            rows += [Sample(dev, to_epoch(r.bench_s), _tilt(r.x_deg), _tilt(r.y_deg), None, r.temp_c, job_id, index,
                            "calibration") for r in readings]
            a = robust_mean(readings)
            settled[role] = {"point": index, "cmd_x_deg": cx, "cmd_y_deg": cy, "n_samples": a.n_used,
                             "t_start_s": to_epoch(a.t_start_s), "t_end_s": to_epoch(a.t_end_s),
                             "ch_x_mean": a.mean[0], "ch_y_mean": a.mean[1], "ch_z_mean": None,
                             "ch_x_std": a.std[0], "ch_y_std": a.std[1], "ch_z_std": None, "temp_c_mean": a.temp_c}
        await write_in_thread(store_point, self.store, job_id, index, rows,
                              {bench.device_ids[role]: settled[role] for role in SENSORS})
        self.events.changed(job_id)

    async def _home_stage(self, job_id: int, bench: BenchRuntime) -> None:
        """The controller refused a move as "not homed" (after power-up): home the stage, then go on."""
        log.info("job %s: the stage of %s is not homed; homing it", job_id, bench.name)
        job = await asyncio.to_thread(self.store.get_job, job_id)
        done, total, phase = job.points_done or 0, job.points_total or 0, job.phase or "measuring"
        await self._progress(job_id, points_done=done, points_total=total, phase="homing")
        await bench.home_stage()
        await self._progress(job_id, points_done=done, points_total=total, phase=phase)

    async def _stage_grid(self, job_id: int, bench: BenchRuntime) -> None:
        job = await asyncio.to_thread(self.store.get_job, job_id)
        params = job.parameters
        req = params["request"]
        fit_pts = [tuple(p) for p in params["fit_points"]]
        val_pts = [tuple(p) for p in params["validation_points"]]
        total = len(fit_pts) + len(val_pts)
        ref_dev, meas_dev = bench.device_ids.get("reference_sensor"), bench.device_ids.get("measurement_sensor")
        if ref_dev is None or meas_dev is None:
            raise InputError(f"bench {bench.name!r} has no registered reference and measurement sensors")
        started_with = params.get("device_ids", {})
        if started_with and started_with != {r: bench.device_ids.get(r) for r in SENSORS}:
            raise InputError(f"the bench's sensors are not those the job started with ({started_with});"
                             " its points cannot be continued with other instruments")
        stored = await asyncio.to_thread(self._points_by_device, job_id)
        done = {p.point for p in stored.get(meas_dev, [])} & {p.point for p in stored.get(ref_dev, [])}
        await self._progress(job_id, points_done=len(done), points_total=total, phase="measuring")
        for i, (x, y) in enumerate(fit_pts):
            if i in done:
                continue
            await self._measure_point(job_id, bench, i, x, y, req)
            done.add(i)
            await self._progress(job_id, points_done=len(done), points_total=total, phase="measuring")
        await self._progress(job_id, points_done=len(done), points_total=total, phase="fitting")
        method = get_method("stage", job.method)
        cols = await asyncio.to_thread(self.fit_columns, job_id, bench, len(fit_pts))
        options = FitOptions(extra={"bench": bench.config.stage_bench(),
                                    "bench_source": f"bench configuration {bench.name}"})
        model = await asyncio.to_thread(method.fit, cols, options)
        model.fit["table_tilt_range_deg"] = table_tilt_range(cols)  # the calibrated range, kept with the record
        await self._progress(job_id, points_done=len(done), points_total=total, phase="validating")
        for k, (x, y) in enumerate(val_pts):
            i = len(fit_pts) + k
            if i in done:
                continue
            await self._measure_point(job_id, bench, i, x, y, req)
            done.add(i)
            await self._progress(job_id, points_done=len(done), points_total=total, phase="validating")
        validation = await asyncio.to_thread(self.validate, job_id, bench, len(fit_pts), method, model)
        conditions = job_conditions(bench, req, list(cols.get("temp_c", [])))
        await write_in_thread(self._conclude, job, meas_dev, "stage", model, validation, conditions, len(fit_pts))

    async def _angle_job(self, job_id: int, bench: BenchRuntime, proc: angles.AngleProcedure) -> None:
        job = await asyncio.to_thread(self.store.get_job, job_id)
        params = job.parameters
        req = params["request"]
        fit_pts, val_pts = list(params["fit_points"]), list(params["validation_points"])
        total = len(fit_pts) + len(val_pts)
        started_with = params.get("device_ids", {})
        if started_with != {r: bench.device_ids.get(r) for r in proc.read_roles}:
            raise InputError(f"the bench's instruments are not those the job started with ({started_with})")
        by_dev = await asyncio.to_thread(self._points_by_device, job_id)
        finished = set.intersection(*[{p.point for p in by_dev.get(bench.device_ids[r], [])} for r in proc.read_roles])
        await self._progress(job_id, points_done=len(finished), points_total=total, phase="measuring")
        method = get_method(proc.kind, job.method)
        model = None
        for i, a in enumerate(fit_pts + val_pts):
            if i == len(fit_pts):
                await self._progress(job_id, points_done=len(finished), points_total=total, phase="fitting")
                model = await asyncio.to_thread(self._fit, method, job_id, len(fit_pts))
            if i in finished:
                continue
            await angles.measure_angle(self.store, job_id, bench, proc, i, a, req)
            finished.add(i)
            phase = "measuring" if i < len(fit_pts) else "validating"
            await self._progress(job_id, points_done=len(finished), points_total=total, phase=phase)
        if model is None:
            await self._progress(job_id, points_done=len(finished), points_total=total, phase="fitting")
            model = await asyncio.to_thread(self._fit, method, job_id, len(fit_pts))
        by_dev = await asyncio.to_thread(self._points_by_device, job_id)
        cols = angles.columns(proc, {d: [p for p in ps if p.point >= len(fit_pts)] for d, ps in by_dev.items()},
                              bench.device_ids, req.get("reference"))
        validation = angles.validation(proc, method, model, cols)
        conditions = job_conditions(bench, req, [p.temp_c_mean for ps in by_dev.values() for p in ps
                                                 if p.temp_c_mean is not None])
        await write_in_thread(self._conclude, job, job.device_id, proc.kind, model, validation, conditions,
                              len(fit_pts))

    def _fit(self, method, job_id: int, n_fit: int):  # type: ignore[no-untyped-def]
        """Blocking (database and the fit): through `asyncio.to_thread`."""
        return method.fit(self.fit_columns(job_id, None, n_fit), FitOptions())

    def _conclude(self, job, device_id: int, kind: str, model, validation: dict, conditions: dict,  # type: ignore[no-untyped-def]
                  n_fit: int) -> None:
        """Blocking (database): the record version, then the job succeeded."""
        req = job.parameters["request"]
        standards = self._standards(req)
        method = get_method(kind, job.method)
        budget = budget_of_record(method, model, self.fit_columns(job.id, None, n_fit) if kind == "stage" else None,
                                  standards, conditions.get("resolution_deg") or {})
        self.store.add_record(device_id, kind, job.method, model.to_json_dict(), operator=job.created_by,
                              validation=validation, temp_c=conditions["temp_c_mean"], job_id=job.id,
                              reference_standards=standards,
                              raw_data={"conditions": conditions, "fit_points": n_fit, "budget": budget})
        self.store.succeed_job(job.id, actor="daemon")

    def _points_by_device(self, job_id: int) -> dict[int, list]:
        out: dict[int, list] = {}
        for p in self.store.settled_points(job_id):
            out.setdefault(p.device_id, []).append(p)
        return out

    def fit_columns(self, job_id: int, bench_or_none, n_fit: int) -> dict[str, np.ndarray]:  # type: ignore[no-untyped-def]
        job = self.store.get_job(job_id)
        proc = angles.PROCEDURES.get(job.parameters.get("request", {}).get("procedure"))
        if proc is not None:
            by_dev = {d: [p for p in ps if p.point < n_fit] for d, ps in self._points_by_device(job_id).items()}
            return angles.columns(proc, by_dev, job.parameters["device_ids"], job.parameters["request"].get("reference"))
        ref_pts, meas_pts = self._points_by_role(job)
        cols = stage_columns([p for p in ref_pts if p.point < n_fit], [p for p in meas_pts if p.point < n_fit])
        if not np.isfinite(cols["temp_c"]).all():
            del cols["temp_c"]  # the same columns the points CSV carries
        return cols

    def _points_by_role(self, job):  # type: ignore[no-untyped-def]
        pts = self.store.settled_points(job.id)
        meas = [p for p in pts if p.device_id == job.device_id]
        ref = [p for p in pts if p.device_id != job.device_id]
        return ref, meas

    def validate(self, job_id: int, bench: BenchRuntime, n_fit: int, method, model) -> dict:  # type: ignore[no-untyped-def]
        job = self.store.get_job(job_id)
        ref_pts, meas_pts = self._points_by_role(job)
        cols = stage_columns([p for p in ref_pts if p.point >= n_fit], [p for p in meas_pts if p.point >= n_fit])
        if cols["point"].size == 0:
            return {"n_points": 0, "rms_deg": None, "max_deg": None}
        out = method.correct(model, cols)
        err = np.hypot(out["tilt_x_deg"] - cols["ref_x_deg"], out["tilt_y_deg"] - cols["ref_y_deg"])
        return {"n_points": int(err.size), "rms_deg": float(np.sqrt(np.mean(err**2))), "max_deg": float(err.max()),
                "compared_with": "reference sensor reading at each validation point",
                # the coverage probability of the points' expanded uncertainties u_x_deg/u_y_deg
                "coverage_probability": COVERAGE,
                "points": [_validation_point(cols, out, i, float(err[i])) for i in range(err.size)]}


def _validation_point(cols: dict, out: dict, i: int, error_deg: float) -> dict:
    """One validation point: the reference sensor's reading, the corrected measurement and its expanded
    uncertainty per axis (what a certificate's validation table shows), and the error's magnitude."""
    point = {"point": int(cols["point"][i]), "stage_x_deg": float(cols["stage_x_deg"][i]),
             "stage_y_deg": float(cols["stage_y_deg"][i]), "error_deg": error_deg}
    for axis in ("x", "y"):
        point[f"reference_{axis}_deg"] = float(cols[f"ref_{axis}_deg"][i])
        point[f"measured_{axis}_deg"] = float(out[f"tilt_{axis}_deg"][i])
        if f"u_tilt_{axis}_deg" in out:
            point[f"u_{axis}_deg"] = float(out[f"u_tilt_{axis}_deg"][i])
    return point
