"""Diagnosis: the model-discrepancy workflow of `tiltlab discrepancy` run on a stored record's points.

It needs no instrument: it reads the settled points the record was fitted on, so it never holds
the bench. The workflow takes seconds of CPU (refits of the physical model), so it runs in a worker
process: the event loop, `/tilt` and the streams keep their pace, and a calibration job may run
on the bench meanwhile. The result (steps, named effects with their evidence and magnitudes, the
gap before and after beside the noise level, the HTML report) is stored once, append-only.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import datetime as dt
import logging
import multiprocessing
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.calibration.model import CalibrationModel
from service.calibration.registry import Method
from service.errors import InputError
from service.storage.models import CalibrationRecord, Diagnosis, DiagnosisResult, utc_now
from service.storage.store import Store

log = logging.getLogger("tiltlab.diagnosis")

SENSORS = ("ref", "meas")
BASELINES = ("kinematic", "linear")
PHASES = ("loading", "analysing", "storing")


@dataclass
class Running:
    """What the daemon knows of a diagnosis before its result is stored."""

    state: str = "queued"
    phase: str | None = None
    started_at: dt.datetime | None = None
    task: asyncio.Task[None] | None = field(default=None, repr=False)


def point_noise(points: list[Any], n_points: int) -> NDArray[np.float64] | None:
    """Per axis, the 1-sigma noise of a settled point (a mean of n readings): the readings' scatter within
    each point, pooled over the points, divided by sqrt(n). None without a scatter (one reading per point)."""
    var = [(p.ch_x_std ** 2 / p.n_samples, p.ch_y_std ** 2 / p.n_samples) for p in points
           if p.point < n_points and p.ch_x_std is not None and p.ch_y_std is not None and p.n_samples > 1]
    if not var:
        return None
    sigma = np.sqrt(np.mean(np.asarray(var), axis=0))
    return sigma if np.all(sigma > 0) else None


def gap(residuals: NDArray[np.float64]) -> dict[str, float]:
    """The gap between model and measured points as one angle per point (x and y together): its RMS and maximum."""
    r = np.hypot(residuals[:, 0], residuals[:, 1])
    return {"rms": float(np.sqrt(np.mean(r**2))), "max": float(np.max(r))}


def run_workflow(columns: dict[str, NDArray[np.float64]], sensor: str, baseline: str, noise_sigma: list[float] | None,
                 noise_dof: float, bench: dict[str, Any] | None, bench_source: str,
                 command: str) -> tuple[dict[str, Any], str]:
    """In the worker process: the workflow of `tiltlab discrepancy` and the figures the service shows of it."""
    from service.discrepancy import noise as noise_mod
    from service.discrepancy.stage import stage_diagnosis
    from service.io.provenance import provenance
    from service.physics.stage import StageBench

    noise: Any = None
    if noise_sigma is not None:
        noise = noise_mod.NoiseLevel(np.asarray(noise_sigma, dtype=float), "scatter within the settled points",
                                     noise_dof,
                                     "the readings' scatter within each settled point, pooled over the points, "
                                     "over the square root of the readings averaged (the noise of a point's mean)")
    report, page, result, _ = stage_diagnosis(
        columns, sensor, baseline, noise, bench=StageBench(**bench) if bench is not None else None,
        inputs={"input": command}, bench_source=bench_source,
        provenance=provenance(command, {}))
    sigma = np.asarray(report["noise_level"], dtype=float)
    summary = {
        "named_effects": list(report["named_effects"]),
        "gap_before_deg": gap(result.fits[0].residuals),
        "gap_after_deg": gap(result.final.residuals),
        "noise_deg": float(np.sqrt(np.sum(sigma**2))),
        "noise_source": report["noise_source"],
        "effects": [{"effect": s["effect"], "summary": s["summary"], "magnitude": s["magnitude"],
                     "evidence": {k: s["evidence"].get(k) for k in ("test", "f_stat", "p_value", "alpha", "delta_bic",
                                                                   "rss_reduction_pct", "where_before")},
                     "rms_before_deg": s["rms_before"], "rms_after_deg": s["rms_after"]}
                    for s in report["steps"]],
        "steps": [{"effect": s["effect"], "summary": s["summary"], "rms_before_deg": s["rms_before"],
                   "rms_after_deg": s["rms_after"]} for s in report["steps"]],
        "untestable": report["skipped"],
        "conclusion": report.get("conclusion"),
        "report": report,
    }
    return summary, page


def fit_adopted(columns: dict[str, NDArray[np.float64]], named: list[str], sensor: str, bench: dict[str, Any],
                bench_source: str, diagnosis: dict[str, Any]) -> dict[str, Any]:
    """In the worker process: the kinematic calibration with the named effects added, as MODEL.json."""
    from service.discrepancy.adopt import adopted_model

    return adopted_model(columns, named, sensor, bench, bench_source, diagnosis).to_json_dict()


def _lower_priority() -> None:
    """The worker yields the CPU to the daemon: the bench's serial exchanges and jobs come first."""
    with contextlib.suppress(OSError, AttributeError):
        os.nice(10)


class DiagnosisRunner:
    """Starts diagnoses and follows them until their result is stored. One worker process serves them in turn."""

    def __init__(self, store: Store, columns_of: Callable[[int, int], dict[str, NDArray[np.float64]]],
                 validate: Callable[[int, int, Method, CalibrationModel], dict[str, Any]]) -> None:
        self.store = store
        self._columns_of = columns_of  # (job_id, n_fit) -> the record's dataset columns
        self._validate = validate  # (job_id, n_fit, method, model) -> the validation figures of a stage record
        self.running: dict[int, Running] = {}
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None

    def _executor(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            self._pool = concurrent.futures.ProcessPoolExecutor(max_workers=1, initializer=_lower_priority,
                                                                mp_context=multiprocessing.get_context("spawn"))
        return self._pool

    def check(self, record: CalibrationRecord, sensor: str, baseline: str) -> None:
        if sensor not in SENSORS:
            raise InputError(f"sensor: {sensor!r} is not one of {', '.join(SENSORS)}")
        if baseline not in BASELINES:
            raise InputError(f"baseline: {baseline!r} is not one of {', '.join(BASELINES)}")
        if record.kind != "stage":
            raise InputError(f"record {record.id} is a {record.kind} record: the diagnosis explains stage records")
        if record.job_id is None:
            raise InputError(f"record {record.id} was not measured by a job of this daemon: it has no stored points")

    async def submit(self, record: CalibrationRecord, sensor: str, baseline: str, actor: str) -> Diagnosis:
        self.check(record, sensor, baseline)
        d: Diagnosis = await asyncio.to_thread(self.store.diagnoses.create_diagnosis, record.id, sensor=sensor, baseline=baseline,
                                    actor=actor)
        run = self.running[d.id] = Running()
        run.task = asyncio.create_task(self._run(d, record), name=f"diagnosis {d.id}")
        return d

    async def _run(self, d: Diagnosis, record: CalibrationRecord) -> None:
        run = self.running[d.id]
        try:
            run.state, run.phase, run.started_at = "running", "loading", utc_now()
            args = await asyncio.to_thread(self._inputs, d, record)
            run.phase = "analysing"
            loop = asyncio.get_running_loop()
            summary, page = await loop.run_in_executor(self._executor(), run_workflow, *args)
            run.phase = "storing"
            await asyncio.to_thread(self.store.diagnoses.finish_diagnosis, d.id, state="succeeded", started_at=run.started_at,
                                    summary=summary, report_html=page, error=None, actor="daemon")
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # the diagnosis fails with the reason; the daemon goes on
            reason = str(exc) if isinstance(exc, InputError) else f"{type(exc).__name__}: {exc}"
            if not isinstance(exc, InputError):
                log.exception("diagnosis %s failed", d.id)
            try:
                await asyncio.to_thread(self.store.diagnoses.finish_diagnosis, d.id, state="failed", started_at=run.started_at,
                                        summary={}, report_html=None, error=reason, actor="daemon")
            except Exception:
                log.exception("diagnosis %s: the failure could not be stored", d.id)
        finally:
            self.running.pop(d.id, None)

    def _inputs(self, d: Diagnosis, record: CalibrationRecord) -> tuple[Any, ...]:
        """Blocking (database): the record's points, the noise of a point and the bench the points came from."""
        assert record.job_id is not None
        n_fit = int((record.raw_data or {}).get("fit_points", 10**9))
        cols = self._columns_of(record.job_id, n_fit)
        job = self.store.jobs.get_job(record.job_id)
        pts = self.store.points.settled_points(record.job_id)
        mine = [p for p in pts if (p.device_id == job.device_id) == (d.sensor == "meas")]
        sigma = point_noise(mine, n_fit)
        dof = float(sum(p.n_samples - 1 for p in mine if p.point < n_fit))
        state = (record.model or {}).get("state", {})
        bench = state.get("bench")
        source = f"record {record.id}'s bench ({state.get('bench_source', 'as calibrated')})"
        command = f"diagnosis {d.id} of record {record.id} (sensor {d.sensor}, baseline {d.baseline})"
        return (cols, d.sensor, d.baseline, None if sigma is None else sigma.tolist(), dof, bench, source, command)

    def state_of(self, d: Diagnosis, result: DiagnosisResult | None) -> dict[str, Any]:
        """The diagnosis as GET /diagnoses/{id} shows it."""
        summary = result.summary if result is not None else {}
        run = self.running.get(d.id)
        state = result.state if result is not None else (run.state if run is not None else "failed")
        return {"id": d.id, "record_id": d.record_id, "sensor": d.sensor, "baseline": d.baseline, "state": state,
                "phase": None if result is not None or run is None else run.phase,
                "created_utc": d.created_at, "created_by": d.created_by,
                "started_utc": result.started_at if result is not None else (run.started_at if run else None),
                "finished_utc": result.finished_at if result is not None else None,
                "named_effects": summary.get("named_effects", []),
                "effects": summary.get("effects", []),
                "gap_before_deg": summary.get("gap_before_deg"), "gap_after_deg": summary.get("gap_after_deg"),
                "noise_deg": summary.get("noise_deg"), "noise_source": summary.get("noise_source"),
                "steps": summary.get("steps", []), "untestable": summary.get("untestable", []),
                "conclusion": summary.get("conclusion"),
                "error": result.error if result is not None else None}

    async def adopt(self, diagnosis_id: int, actor: str) -> CalibrationRecord:
        """A new record version of the diagnosed record's device whose model has the named effects, fitted on the
        same points through the calibration code, with its validation figures (a draft like any new record)."""
        from service.calibration.model import CalibrationModel
        from service.calibration.registry import get_method
        from service.discrepancy.adopt import effects_to_add
        from service.storage.errors import ConflictError

        d, result = await asyncio.to_thread(self.store.diagnoses.get_diagnosis, diagnosis_id)
        if result is None or result.state != "succeeded":
            state = "running" if result is None else f"failed ({result.error})"
            raise ConflictError(f"diagnosis {diagnosis_id} is {state}: only a finished diagnosis can be adopted")
        named = list(result.summary.get("named_effects", []))
        try:
            effects_to_add(named, d.sensor)
        except InputError as exc:
            raise ConflictError(str(exc)) from None
        record = await asyncio.to_thread(self.store.records.get_record, d.record_id)
        assert record.job_id is not None  # a diagnosed record has stored points
        raw = dict(record.raw_data or {})
        n_fit = int(raw.get("fit_points", 10**9))
        cols = await asyncio.to_thread(self._columns_of, record.job_id, n_fit)
        state = (record.model or {}).get("state", {})
        if "bench" not in state:
            raise ConflictError(f"record {record.id} does not state the bench it was calibrated on")
        source = f"record {record.id}'s bench ({state.get('bench_source', 'as calibrated')})"
        origin = {"id": d.id, "record_id": record.id, "sensor": d.sensor, "baseline": d.baseline,
                  "what": f"diagnosis {d.id} of record {record.id} (v{record.version})"}
        loop = asyncio.get_running_loop()
        model_doc = await loop.run_in_executor(self._executor(), fit_adopted, cols, named, d.sensor, state["bench"],
                                               source, origin)
        method = get_method("stage", "kinematic")
        model = CalibrationModel.from_json_dict(model_doc, f"diagnosis {d.id}")
        validation = await asyncio.to_thread(self._validate, record.job_id, n_fit, method, model)
        raw.pop("job_id", None)
        raw.update({"diagnosis_id": d.id, "added_effects": model.state.get("added_effects", []),
                    "adopted_from_record_id": record.id})
        return await asyncio.to_thread(
            self.store.records.add_record, record.device_id, "stage", "kinematic", model_doc, operator=actor,
            validation=validation, temp_c=record.temp_c, job_id=record.job_id,
            reference_standards=record.reference_standards, raw_data=raw)

    async def wait(self, diagnosis_id: int) -> None:
        run = self.running.get(diagnosis_id)
        if run is not None and run.task is not None:
            await asyncio.shield(run.task)

    async def shutdown(self) -> None:
        for run in list(self.running.values()):
            if run.task is not None:
                run.task.cancel()
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
