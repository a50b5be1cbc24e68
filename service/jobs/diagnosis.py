"""Diagnosis: the model-discrepancy workflow of `tiltlab discrepancy` run on a stored record's
points.

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
import signal
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NotRequired, TypedDict, cast

import numpy as np
from numpy.typing import NDArray

from service.bench.runtime import BenchBusy, BenchRuntime
from service.calibration.methods.stage.chain import IN_CHAIN
from service.calibration.model import CalibrationModel, ParameterJSON, StageBenchJSON
from service.calibration.registry import get_method
from service.discrepancy.adopt import (
    AdoptedFrom,
    AdoptionVerdict,
    NothingToAdopt,
    effects_to_add,
    record_effects,
    worm_axes_of,
)
from service.discrepancy.report_types import (
    DiscrepancyReport,
    EffectReason,
    Magnitude,
    StepReport,
)
from service.errors import InputError
from service.jobs.job_parameters import RequestJSON
from service.jobs.manager import JobManager
from service.jobs.requests import CalibrationRequest
from service.storage.errors import ConflictError
from service.storage.models import (
    CalibrationJob,
    CalibrationRecord,
    Diagnosis,
    DiagnosisResult,
    JobState,
    utc_now,
)
from service.storage.store import Store

if TYPE_CHECKING:
    from service.discrepancy.design import MeasurementPlanJSON

log = logging.getLogger("tiltlab.diagnosis")

SENSORS = ("ref", "meas")
BASELINES = ("kinematic", "linear")
PHASES = ("loading", "planning", "measuring", "analysing", "storing")
WORKER_END_S = 5.0  # a worker asked to end (SIGTERM) is killed after this long
# bench seconds a point takes when the record's job gives no timing
DEFAULT_SECONDS_PER_POINT = 30.0


class Gap(TypedDict):
    """The gap between model and points as one angle per point (x and y together), deg."""

    rms: float
    max: float


class EvidenceSummary(TypedDict):
    """The test that named an effect, as the diagnosis shows it (the report has the rest)."""

    test: str
    f_stat: float
    p_value: float
    alpha: float
    delta_bic: float
    rss_reduction_pct: float
    where_before: list[str]


class EffectSummary(TypedDict):
    """One named effect: its size, its evidence, and whether the record can adopt it."""

    effect: str
    summary: str
    magnitude: Magnitude
    evidence: EvidenceSummary
    rms_before_deg: list[float]  # per axis
    rms_after_deg: list[float]
    adoptable: bool
    adoption: str | None  # the verdict's reason
    measurement: str | None  # what would let it be adopted


class StepSummary(TypedDict):
    """One step of the chain of named effects."""

    effect: str
    summary: str
    rms_before_deg: list[float]
    rms_after_deg: list[float]


class ResidualMaps(TypedDict):
    """Per point diagnosed, its stand, approach and residual before and after the named effects."""

    stage_deg: list[list[float]]  # [x, y] per point
    approach: list[list[float]]  # [dir_x, dir_y]
    before_deg: list[list[float]]  # residual [x, y], the baseline alone
    after_deg: list[list[float]]  # with the named effects
    unit: str
    what: str


class DiagnosisData(TypedDict):
    """The points diagnosed: the record's, and those of measurements made for it."""

    record_id: int
    record_job_id: int | None
    measurement_job_ids: list[int]
    n_points: int | None


class MeasurementBefore(TypedDict):
    """What a `measure` diagnosis's first look at the record's points alone showed."""

    named_effects: list[str]
    gap_before_deg: Gap
    gap_after_deg: Gap
    untestable: list[EffectReason]
    adoptable: bool
    adoption: list[AdoptionVerdict]
    n_points: int


class MeasurementSummary(TypedDict):
    """A `measure` diagnosis's measurement: the plan, the job that measured it, the first look."""

    plan: MeasurementPlanJSON | None
    job_id: int | None
    before: NotRequired[MeasurementBefore]  # once the diagnosis is stored


class DiagnosisSummary(TypedDict, total=False):
    """A diagnosis's result as stored (JSON) and shown. `run_workflow` fills every key but `data`
    and `measurement`, which the runner adds; a failed diagnosis stores at most `measurement`, and
    one stored by an older version may lack later keys: read them with .get."""

    named_effects: list[str]
    gap_before_deg: Gap
    gap_after_deg: Gap
    noise_deg: float
    noise_source: str
    effects: list[EffectSummary]
    steps: list[StepSummary]
    untestable: list[EffectReason]
    adoptable: bool
    adoption: list[AdoptionVerdict]
    measurement_plan: MeasurementPlanJSON
    n_points: int
    residual_maps: ResidualMaps
    conclusion: str
    report: DiscrepancyReport
    data: DiagnosisData
    measurement: MeasurementSummary


class DiagnosisPlanJSON(TypedDict):
    """What a record's points show and cannot test, and the measurement `measure` would run."""

    record_id: int
    sensor: str
    baseline: str
    named_effects: list[str]
    gap_before_deg: Gap
    gap_after_deg: Gap
    noise_deg: float
    untestable: list[EffectReason]
    adoptable: bool
    adoption: list[AdoptionVerdict]
    n_points: int
    plan: MeasurementPlanJSON


class DiagnosisState(TypedDict):
    """A diagnosis as GET /diagnoses/{id} shows it (the stored result's keys null until it ends)."""

    id: int
    record_id: int
    sensor: str
    baseline: str
    state: str
    phase: str | None
    created_utc: dt.datetime
    created_by: str
    started_utc: dt.datetime | None
    finished_utc: dt.datetime | None
    named_effects: list[str]
    effects: list[EffectSummary]
    gap_before_deg: Gap | None
    gap_after_deg: Gap | None
    noise_deg: float | None
    noise_source: str | None
    steps: list[StepSummary]
    untestable: list[EffectReason]
    adoptable: bool | None
    adoption: list[AdoptionVerdict]
    measurement_plan: MeasurementPlanJSON | None
    measurement: MeasurementSummary | None
    residual_maps: ResidualMaps | None
    data: DiagnosisData | None
    conclusion: str | None
    error: str | None


def stored_summary(result: DiagnosisResult) -> DiagnosisSummary:
    """A stored result's summary: the JSON this module wrote (`DiagnosisSummary`)."""
    return cast(DiagnosisSummary, result.summary)


@dataclass
class Running:
    """What the daemon knows of a diagnosis before its result is stored."""

    state: str = "queued"
    phase: str | None = None
    started_at: dt.datetime | None = None
    task: asyncio.Task[None] | None = field(default=None, repr=False)
    measure: bool = False  # measure what the stored points cannot test first
    plan: MeasurementPlanJSON | None = None  # the measurement planned, once it is
    job_id: int | None = None  # the job measuring it


def gap(residuals: NDArray[np.float64]) -> Gap:
    """The gap between model and measured points as one angle per point (x and y together): its RMS
    and maximum."""
    per_point = np.hypot(residuals[:, 0], residuals[:, 1])
    return {"rms": float(np.sqrt(np.mean(per_point**2))), "max": float(np.max(per_point))}


@dataclass(frozen=True)
class WorkflowInputs:
    """What the worker needs for one diagnosis: the points, the bench and what the record has."""

    columns: dict[str, NDArray[np.float64]]
    sensor: str
    baseline: str
    bench: StageBenchJSON | None
    bench_source: str
    command: str
    have: frozenset[str] = frozenset()  # effects the record fits already
    # effects the record was adopted with (an adopted version keeps them)
    keep: tuple[str, ...] = ()
    worm_axes: tuple[str, ...] = ()  # stages whose worm error the record fits already
    seconds_per_point: float = 0.0
    estimate_source: str = ""


def run_workflow(w: WorkflowInputs) -> tuple[DiagnosisSummary, str]:
    """In the worker process: the workflow of `tiltlab discrepancy`, the figures the service shows
    of it, whether each named effect can be adopted from these points (by the refit adopting makes),
    and the measurement that would test what the points cannot."""
    from service.discrepancy.adopt import adoption, seen_labels_of
    from service.discrepancy.design import needs_of, plan_measurement
    from service.discrepancy.stage import stage_diagnosis
    from service.discrepancy.stage_data import StageData
    from service.discrepancy.workflow import WEAK_SEPARABILITY
    from service.io.provenance import provenance
    from service.physics.stage import StageBench

    # The readings' scatter within a settled point is the sensors' noise alone: a point's mean also
    # carries the stage's positioning error of its stand (a repeatability the scatter at one stand
    # cannot show), so it is only a lower bound of a point's noise. The diagnosis estimates the
    # noise of a point from the points.
    noise: Any = None
    bench = StageBench(**w.bench) if w.bench is not None else None
    report, page, result, fam = stage_diagnosis(
        w.columns,
        w.sensor,
        w.baseline,
        noise,
        bench=bench,
        inputs={"input": w.command},
        bench_source=w.bench_source,
        provenance=provenance(w.command, {}),
    )
    sigma = np.asarray(report["noise_level"], dtype=float)
    named = list(report["named_effects"])
    seen = seen_labels_of(result.steps)
    verdicts = [
        verdict.as_dict()
        for verdict in adoption(
            w.columns, named, w.sensor, bench, w.bench_source, w.have, seen, w.keep, w.worm_axes
        )
    ]
    by_effect = {verdict["effect"]: verdict for verdict in verdicts}
    hw = bench or StageBench()
    data = StageData.from_columns(w.columns, w.sensor, hw)
    needs = needs_of(report, fam.active, verdicts, WEAK_SEPARABILITY, data)
    plan = plan_measurement(data, hw, hw.travel_deg, needs, w.seconds_per_point, w.estimate_source)
    summary: DiagnosisSummary = {
        "named_effects": named,
        "gap_before_deg": gap(result.fits[0].residuals),
        "gap_after_deg": gap(result.final.residuals),
        "noise_deg": float(np.sqrt(np.sum(sigma**2))),
        "noise_source": report["noise_source"],
        "effects": [
            _effect_summary(step, by_effect.get(step["effect"])) for step in report["steps"]
        ],
        "steps": [
            {
                "effect": step["effect"],
                "summary": step["summary"],
                "rms_before_deg": step["rms_before"],
                "rms_after_deg": step["rms_after"],
            }
            for step in report["steps"]
        ],
        "untestable": report["skipped"],
        "adoptable": any(verdict["adoptable"] for verdict in verdicts),
        "adoption": verdicts,
        "measurement_plan": plan.as_dict(),
        "n_points": int(len(result.fits[0].residuals)),
        "residual_maps": residual_maps(w.columns, result.fits[0].residuals, result.final.residuals),
        "conclusion": report["conclusion"],
        "report": report,
    }
    return summary, page


def _effect_summary(step: StepReport, verdict: AdoptionVerdict | None) -> EffectSummary:
    """A named effect as the diagnosis shows it: the report's step, the evidence's figures, and the
    adoption verdict on it (not adoptable without one)."""
    evidence = step["evidence"]
    return {
        "effect": step["effect"],
        "summary": step["summary"],
        "magnitude": step["magnitude"],
        "evidence": {
            "test": evidence["test"],
            "f_stat": evidence["f_stat"],
            "p_value": evidence["p_value"],
            "alpha": evidence["alpha"],
            "delta_bic": evidence["delta_bic"],
            "rss_reduction_pct": evidence["rss_reduction_pct"],
            "where_before": evidence["where_before"],
        },
        "rms_before_deg": step["rms_before"],
        "rms_after_deg": step["rms_after"],
        "adoptable": verdict["adoptable"] if verdict is not None else False,
        "adoption": verdict["reason"] if verdict is not None else None,
        "measurement": verdict["measurement"] if verdict is not None else None,
    }


def residual_maps(
    columns: dict[str, NDArray[np.float64]], before: NDArray[np.float64], after: NDArray[np.float64]
) -> ResidualMaps:
    """The residual (measured - model) at every point diagnosed, with the baseline alone and with
    the named effects: the two maps a page draws side by side to show the gap shrink."""

    def rows(pairs: NDArray[np.float64]) -> list[list[float]]:
        return [[round(float(x), 9), round(float(y), 9)] for x, y in np.asarray(pairs, dtype=float)]

    pts = np.column_stack([columns["stage_x_deg"], columns["stage_y_deg"]])
    dirs = np.column_stack(
        [columns.get("dir_x", np.ones(len(pts))), columns.get("dir_y", np.ones(len(pts)))]
    )
    return {
        "stage_deg": rows(pts),
        "approach": rows(dirs),
        "before_deg": rows(before),
        "after_deg": rows(after),
        "unit": "deg",
        "what": "residual x, y (measured - model) per point: the baseline alone (before) and with "
        "the named effects (after)",
    }


def fit_adopted(
    columns: dict[str, NDArray[np.float64]],
    effects: list[str],
    sensor: str,
    bench: StageBenchJSON,
    bench_source: str,
    diagnosis: AdoptedFrom,
    have: frozenset[str],
    keep: tuple[str, ...],
    worm_axes: list[str],
) -> Mapping[str, object]:
    """In the worker process: the kinematic calibration with the adoptable named effects added, as
    MODEL.json."""
    from service.discrepancy.adopt import adopted_model

    return adopted_model(
        columns, effects, sensor, bench, bench_source, diagnosis, have, keep, worm_axes
    ).to_json_dict()


def seconds_per_point(points: list[Any], clock_speed: float) -> tuple[float, str]:
    """Bench seconds a point took in a job (the median time between consecutive points' last
    readings), and where that figure comes from."""
    ends = sorted(float(point.t_end_s) for point in points)
    steps = np.diff(ends)
    steps = steps[steps > 0]
    if steps.size == 0:
        return DEFAULT_SECONDS_PER_POINT, "a default (the record's job gives no timing)"
    per = float(np.median(steps)) * clock_speed
    return per, f"the record's own job: a median {per:.3g} s of bench time between its points"


def merged_columns(parts: list[dict[str, NDArray[np.float64]]]) -> dict[str, NDArray[np.float64]]:
    """Several jobs' points as one set of dataset columns: the columns all of them carry, point
    numbers made unique (a job's point 3 is not another job's point 3)."""
    if len(parts) == 1:
        return parts[0]
    keys = [k for k in parts[0] if all(k in part for part in parts[1:])]
    out = {k: np.concatenate([np.asarray(part[k], dtype=float) for part in parts]) for k in keys}
    if "point" in out:
        offset = 0.0
        numbered = []
        for part in parts:
            numbered.append(np.asarray(part["point"], dtype=float) + offset)
            offset += float(np.max(part["point"])) + 1.0 if len(part["point"]) else 0.0
        out["point"] = np.concatenate(numbered)
    return out


PARENT_CHECK_S = 0.5  # how often a worker looks whether the daemon that started it is still there


def _worker_start(parent_pid: int) -> None:
    """In each worker process: yield the CPU to the daemon (the bench's serial exchanges and jobs
    come first), leave Ctrl-C to the daemon (which ends its workers itself), and end as soon as the
    daemon is gone, however it went (a SIGKILL leaves no chance to end the workers): a watch on the
    parent process."""
    with contextlib.suppress(OSError, AttributeError):
        os.nice(10)
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch() -> None:
        while True:
            time.sleep(PARENT_CHECK_S)
            if os.getppid() != parent_pid:
                os._exit(0)  # the daemon is gone: nobody will read the result

    threading.Thread(target=watch, name="tiltlab-worker-parent-watch", daemon=True).start()


def _diagnosis_command(
    diagnosis: Diagnosis, record: CalibrationRecord, extra_jobs: list[int]
) -> str:
    """The diagnosis in words, as its report states its input: the record, the measurement jobs
    whose points were added, the sensor and the baseline."""
    extra = (
        f", with the points of measurement job{'s' * (len(extra_jobs) > 1)} "
        f"{', '.join(map(str, extra_jobs))}"
        if extra_jobs
        else ""
    )
    return (
        f"diagnosis {diagnosis.id} of record {record.id}{extra} (sensor {diagnosis.sensor}, "
        f"baseline {diagnosis.baseline})"
    )


def _worm_axes(model: Mapping[str, object]) -> tuple[str, ...]:
    """The stages whose worm (periodic) error the record fits already: any of its terms free."""
    # a stored model (MODEL.json) states its parameters so
    params = cast("Mapping[str, ParameterJSON]", model.get("parameters", {}))
    return tuple(
        ax
        for ax in ("x", "y")
        if any(
            not (params.get(f"periodic_error.{ax}_{t}_deg") or {"fixed": True}).get("fixed", False)
            for t in ("sin", "cos", "amp")
        )
    )


def _measurement_summary(first: DiagnosisSummary, extra_jobs: list[int]) -> MeasurementSummary:
    """What a `measure` diagnosis keeps of its measurement: the plan, the job that measured it,
    and the first look's figures from the record's points alone (`run_workflow`'s, all there)."""
    return {
        "plan": first["measurement_plan"],
        "job_id": extra_jobs[0] if extra_jobs else None,
        "before": {
            "named_effects": first["named_effects"],
            "gap_before_deg": first["gap_before_deg"],
            "gap_after_deg": first["gap_after_deg"],
            "untestable": first["untestable"],
            "adoptable": first["adoptable"],
            "adoption": first["adoption"],
            "n_points": first["n_points"],
        },
    }


def _measurement_jobs(summary: DiagnosisSummary) -> list[int]:
    """The measurement jobs whose points a diagnosis added to the record's."""
    data = summary.get("data")
    return [int(j) for j in (data.get("measurement_job_ids", []) if data else [])]


def _progress(
    result: DiagnosisResult | None, run: Running | None
) -> tuple[str, str | None, dt.datetime | None]:
    """A diagnosis's state, phase and start: as stored once it ended, else as the daemon follows
    it (a diagnosis neither stored nor followed failed: the daemon stopped meanwhile)."""
    if result is not None:
        return result.state, None, result.started_at
    if run is None:
        return "failed", None, None
    return run.state, run.phase, run.started_at


def _measurement_shown(summary: DiagnosisSummary, run: Running | None) -> MeasurementSummary | None:
    """The measurement a diagnosis shows: as stored, else (a `measure` diagnosis still running) the
    plan and the job so far."""
    measurement = summary.get("measurement")
    if measurement is None and run is not None and run.measure:
        return {"plan": run.plan, "job_id": run.job_id}
    return measurement


def _effects_to_add(named: list[str], sensor: str, have: frozenset[str]) -> list[str]:
    """The named effects the record can add, as they are; ConflictError (409) with the reason when
    it can add none of them."""
    try:
        return effects_to_add(named, sensor, have)
    except InputError as exc:
        raise ConflictError(str(exc)) from None


def _blocked(verdicts: list[AdoptionVerdict], have: frozenset[str]) -> list[AdoptionVerdict]:
    """The verdicts on effects the record could add (neither in the chain nor fitted already) that
    these points do not let it adopt."""
    return [
        verdict
        for verdict in verdicts
        if not verdict.get("adoptable")
        and verdict["effect"] not in IN_CHAIN
        and verdict["effect"] not in have
    ]


def _why_blocked(blocked: list[AdoptionVerdict]) -> str:
    """Each blocked effect with the reason, and the measurement that would let it be adopted."""
    return "; ".join(
        f"{verdict['effect']}: {verdict['reason']}"
        + (f" (what would: {verdict['measurement']})" if verdict.get("measurement") else "")
        for verdict in blocked
    )


def _why_not_adoptable(summary: DiagnosisSummary, effect: str) -> str:
    """The reason the diagnosis gave for not finding `effect` adoptable, as a ": ..." suffix (empty
    without one)."""
    verdict = next(
        (verdict for verdict in summary.get("adoption") or [] if verdict.get("effect") == effect),
        None,
    )
    return f": {verdict['reason']}" if verdict is not None and verdict.get("reason") else ""


class DiagnosesBusy(RuntimeError):
    """As many diagnoses as the daemon takes are queued or running already."""


class DiagnosisRunner:
    """Starts diagnoses and follows them until their result is stored. One worker process serves
    them in turn.

    A diagnosis with `measure` first looks at the record's points, then (when they cannot test a
    candidate) runs the planned measurement as a job on the record's bench through the job manager,
    and diagnoses all the points."""

    def __init__(self, store: Store, jobs: JobManager, *, max_diagnoses: int = 4) -> None:
        self.store = store
        self.jobs = jobs
        # queued and running at once; one more is refused (DiagnosesBusy)
        self.max_diagnoses = max_diagnoses
        # plans (`plan_only`) waiting for or in the worker: they count against the bound too
        self.planning = 0
        self.running: dict[int, Running] = {}
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None

    def _executor(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            self._pool = concurrent.futures.ProcessPoolExecutor(
                max_workers=1,
                initializer=_worker_start,
                initargs=(os.getpid(),),
                mp_context=multiprocessing.get_context("spawn"),
            )
        return self._pool

    def check(self, record: CalibrationRecord, sensor: str, baseline: str) -> None:
        if sensor not in SENSORS:
            raise InputError(f"sensor: {sensor!r} is not one of {', '.join(SENSORS)}")
        if baseline not in BASELINES:
            raise InputError(f"baseline: {baseline!r} is not one of {', '.join(BASELINES)}")
        if record.kind != "stage":
            raise InputError(
                f"record {record.id} is a {record.kind} record: the diagnosis explains stage "
                "records"
            )
        if record.job_id is None:
            raise InputError(
                f"record {record.id} was not measured by a job of this daemon: it has no stored "
                "points"
            )

    def bench_for(self, record: CalibrationRecord) -> BenchRuntime:
        """The bench a measurement for the record runs on: the one carrying its device, free now
        (else 409)."""
        bench = self.jobs.bench_of_device(record.device_id)
        if bench is None:
            raise ConflictError(
                f"measure: record {record.id}'s instrument is on no bench this daemon runs, so it "
                "cannot measure for it"
            )
        if bench.holder is not None:
            raise BenchBusy(
                f"bench {bench.name!r} is held by {bench.holder}: a measurement needs it free"
            )
        return bench

    async def submit(
        self,
        record: CalibrationRecord,
        sensor: str,
        baseline: str,
        actor: str,
        measure: bool = False,
    ) -> Diagnosis:
        self.check(record, sensor, baseline)
        self._refuse_when_busy()
        if measure:
            self.bench_for(record)
        diagnosis: Diagnosis = await asyncio.to_thread(
            self.store.diagnoses.create_diagnosis,
            record.id,
            sensor=sensor,
            baseline=baseline,
            actor=actor,
        )
        run = self.running[diagnosis.id] = Running(measure=measure)
        run.task = asyncio.create_task(
            self._run(diagnosis, record, actor), name=f"diagnosis {diagnosis.id}"
        )
        return diagnosis

    def _refuse_when_busy(self) -> None:
        if len(self.running) + self.planning >= self.max_diagnoses:
            raise DiagnosesBusy(
                f"{len(self.running) + self.planning} diagnoses and plans are queued or running, as"
                " many as the daemon takes"
                " (TILTLAB_MAX_DIAGNOSES); ask again once one has finished"
            )

    async def plan(
        self, record: CalibrationRecord, sensor: str, baseline: str
    ) -> DiagnosisPlanJSON:
        """What the record's points cannot test and the measurement that would, without moving
        anything (or storing a diagnosis): the look `measure` takes first."""
        self.check(record, sensor, baseline)
        self._refuse_when_busy()
        probe = Diagnosis(
            id=0,
            record_id=record.id,
            sensor=sensor,
            baseline=baseline,
            created_by="",
            created_at=utc_now(),
        )
        self.planning += 1
        try:
            inputs = await asyncio.to_thread(self._inputs, probe, record, [])
            loop = asyncio.get_running_loop()
            summary, _ = await loop.run_in_executor(self._executor(), run_workflow, inputs)
        finally:
            self.planning -= 1
        return {
            "record_id": record.id,
            "sensor": sensor,
            "baseline": baseline,
            "named_effects": summary["named_effects"],
            "gap_before_deg": summary["gap_before_deg"],
            "gap_after_deg": summary["gap_after_deg"],
            "noise_deg": summary["noise_deg"],
            "untestable": summary["untestable"],
            "adoptable": summary["adoptable"],
            "adoption": summary["adoption"],
            "n_points": summary["n_points"],
            "plan": summary["measurement_plan"],
        }

    async def _run(self, d: Diagnosis, record: CalibrationRecord, actor: str) -> None:
        run = self.running[d.id]
        try:
            run.state, run.phase, run.started_at = "running", "loading", utc_now()
            loop = asyncio.get_running_loop()
            extra_jobs: list[int] = []
            first: DiagnosisSummary | None = None
            if run.measure:
                first, extra_jobs = await self._look_and_measure(d, record, actor, run)
            run.phase = "loading"
            inputs = await asyncio.to_thread(self._inputs, d, record, extra_jobs)
            run.phase = "analysing"
            summary, page = await loop.run_in_executor(self._executor(), run_workflow, inputs)
            summary["data"] = {
                "record_id": record.id,
                "record_job_id": record.job_id,
                "measurement_job_ids": extra_jobs,
                "n_points": summary.get("n_points"),
            }
            if first is not None:
                summary["measurement"] = _measurement_summary(first, extra_jobs)
            run.phase = "storing"
            await asyncio.to_thread(
                self.store.diagnoses.finish_diagnosis,
                d.id,
                state="succeeded",
                started_at=run.started_at,
                summary=summary,
                report_html=page,
                error=None,
                actor="daemon",
            )
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # the diagnosis fails with the reason; the daemon goes on
            reason = (
                str(exc)
                if isinstance(exc, InputError | BenchBusy)
                else f"{type(exc).__name__}: {exc}"
            )
            if not isinstance(exc, InputError | BenchBusy):
                log.exception("diagnosis %s failed", d.id)
            await self._store_failure(d, run, reason)
        finally:
            self.running.pop(d.id, None)

    async def _look_and_measure(
        self, diagnosis: Diagnosis, record: CalibrationRecord, actor: str, run: Running
    ) -> tuple[DiagnosisSummary, list[int]]:
        """A `measure` diagnosis's first look at the record's points, then the measurement it plans
        run as a job (when the plan has points): the look, and the job whose points it adds."""
        run.phase = "planning"
        loop = asyncio.get_running_loop()
        inputs = await asyncio.to_thread(self._inputs, diagnosis, record, [])
        looked, _ = await loop.run_in_executor(self._executor(), run_workflow, inputs)
        plan = run.plan = looked["measurement_plan"]
        if not plan["n_points"]:
            return looked, []
        run.phase = "measuring"
        job = await self._measure(diagnosis, record, plan, actor)
        run.job_id = job.id
        ended = await self.jobs.wait_for(job.id)
        if ended.state != JobState.SUCCEEDED:
            raise InputError(
                f"the planned measurement (job {job.id}) {ended.state}"
                + (f": {ended.failure_reason}" if ended.failure_reason else "")
                + "; its points are kept, the diagnosis is not made"
            )
        return looked, [job.id]

    async def _store_failure(self, diagnosis: Diagnosis, run: Running, reason: str) -> None:
        """The diagnosis stored as failed with the reason (and the measurement it planned, if any);
        a failure that cannot be stored is logged, the daemon goes on."""
        try:
            await asyncio.to_thread(
                self.store.diagnoses.finish_diagnosis,
                diagnosis.id,
                state="failed",
                started_at=run.started_at,
                summary={"measurement": {"plan": run.plan, "job_id": run.job_id}}
                if run.plan
                else {},
                report_html=None,
                error=reason,
                actor="daemon",
            )
        except Exception:
            log.exception("diagnosis %s: the failure could not be stored", diagnosis.id)

    async def _measure(
        self, d: Diagnosis, record: CalibrationRecord, plan: MeasurementPlanJSON, actor: str
    ) -> CalibrationJob:
        """The planned points as a job on the record's bench, settled and read as the record's own
        job read its."""
        assert record.job_id is not None
        bench = self.bench_for(record)
        own = (await asyncio.to_thread(self.store.jobs.get_job, record.job_id)).parameters.get(
            "request", {}
        )
        request: RequestJSON = {
            "bench": bench.name,
            "procedure": "stage-grid",
            "method": record.method,
            "grid": {
                "points": [[point["stage_x_deg"], point["stage_y_deg"]] for point in plan["points"]]
            },
            "samples_per_point": own.get("samples_per_point", 10),
            "validation": {"n_points": 0},
            "note": f"the measurement diagnosis {d.id} of record {record.id} planned",
        }
        if own.get("settle"):
            request["settle"] = own["settle"]
        # how each point is settled and read: a stage grid's rules
        CalibrationRequest.model_validate(request)
        points = [
            [point["stage_x_deg"], point["stage_y_deg"], point["dir_x"], point["dir_y"]]
            for point in plan["points"]
        ]
        return await self.jobs.submit_measurement(
            bench,
            record.device_id,
            request,
            points,
            {
                "diagnosis_id": d.id,
                "record_id": record.id,
                "plan": {
                    "parts": plan["parts"],
                    "cannot": plan["cannot"],
                    "estimated_bench_s": plan["estimated_bench_s"],
                },
            },
            actor,
        )

    def _inputs(
        self, d: Diagnosis, record: CalibrationRecord, extra_jobs: list[int]
    ) -> WorkflowInputs:
        """Blocking (database): the record's points (with those of measurements made for it), the
        noise of a point, the bench the points came from and what the record fits already."""
        assert record.job_id is not None
        n_fit = int((record.raw_data or {}).get("fit_points", 10**9))
        cols = self._merged_columns(record.job_id, n_fit, extra_jobs)
        job = self.store.jobs.get_job(record.job_id)

        # the diagnosed sensor's settled points of a job
        def sensor_points(job_id: int) -> list[Any]:
            return [
                point
                for point in self.store.points.settled_points(job_id)
                if (point.device_id == job.device_id) == (d.sensor == "meas")
            ]

        own_points = [point for point in sensor_points(record.job_id) if point.point < n_fit]
        model = record.model or {}
        state = model.get("state", {})
        bench = state.get("bench")
        source = f"record {record.id}'s bench ({state.get('bench_source', 'as calibrated')})"
        speed = float(((record.raw_data or {}).get("conditions") or {}).get("clock_speed") or 1.0)
        per, source_text = seconds_per_point(own_points, speed)
        return WorkflowInputs(
            cols,
            d.sensor,
            d.baseline,
            bench,
            source,
            _diagnosis_command(d, record, extra_jobs),
            frozenset(record_effects(model)),
            tuple(state.get("added_effects", [])),
            _worm_axes(model),
            per,
            source_text,
        )

    def _merged_columns(
        self, job_id: int, n_fit: int, extra_jobs: list[int]
    ) -> dict[str, NDArray[np.float64]]:
        """Blocking (database): the first `n_fit` points of the record's job and every point of the
        measurement jobs made for it, as one set of columns."""
        return merged_columns(
            [self.jobs.fit_columns(job_id, n_fit)]
            + [self.jobs.fit_columns(j, 10**9) for j in extra_jobs]
        )

    def state_of(self, d: Diagnosis, result: DiagnosisResult | None) -> DiagnosisState:
        """The diagnosis as GET /diagnoses/{id} shows it."""
        summary = stored_summary(result) if result is not None else DiagnosisSummary()
        run = self.running.get(d.id)
        state, phase, started = _progress(result, run)
        return {
            "id": d.id,
            "record_id": d.record_id,
            "sensor": d.sensor,
            "baseline": d.baseline,
            "state": state,
            "phase": phase,
            "created_utc": d.created_at,
            "created_by": d.created_by,
            "started_utc": started,
            "finished_utc": result.finished_at if result is not None else None,
            "named_effects": summary.get("named_effects", []),
            "effects": summary.get("effects", []),
            "gap_before_deg": summary.get("gap_before_deg"),
            "gap_after_deg": summary.get("gap_after_deg"),
            "noise_deg": summary.get("noise_deg"),
            "noise_source": summary.get("noise_source"),
            "steps": summary.get("steps", []),
            "untestable": summary.get("untestable", []),
            "adoptable": summary.get("adoptable"),
            "adoption": summary.get("adoption", []),
            "measurement_plan": summary.get("measurement_plan"),
            "measurement": _measurement_shown(summary, run),
            "residual_maps": summary.get("residual_maps"),
            "data": summary.get("data"),
            "conclusion": summary.get("conclusion"),
            "error": result.error if result is not None else None,
        }

    async def adopt(
        self, diagnosis_id: int, actor: str, chosen: list[str] | None = None
    ) -> CalibrationRecord:
        """A new record version of the diagnosed record's device whose model has the adoptable named
        effects (of them, those `chosen`), fitted on the points the diagnosis used through the
        calibration code, with its validation figures (a draft like any new record). 409 when the
        diagnosis named nothing the record can adopt, or a chosen effect it did not find adoptable,
        with the reason."""
        diagnosis, result = await self._succeeded(diagnosis_id)
        record = await asyncio.to_thread(self.store.records.get_record, diagnosis.record_id)
        assert record.job_id is not None  # a diagnosed record has stored points
        model_doc_before = record.model or {}
        state = model_doc_before.get("state", {})
        have = frozenset(record_effects(model_doc_before))
        summary = stored_summary(result)
        named = list(summary.get("named_effects", []))
        effects = self._adoptable(diagnosis_id, summary, named, diagnosis.sensor, have)
        if chosen is not None:
            effects = self._chosen(diagnosis_id, summary, named, effects, chosen)
        raw = dict(record.raw_data or {})
        n_fit = int(raw.get("fit_points", 10**9))
        extra_jobs = _measurement_jobs(summary)
        cols = await asyncio.to_thread(self._merged_columns, record.job_id, n_fit, extra_jobs)
        if "bench" not in state:
            raise ConflictError(f"record {record.id} does not state the bench it was calibrated on")
        source = f"record {record.id}'s bench ({state.get('bench_source', 'as calibrated')})"
        origin: AdoptedFrom = {
            "id": diagnosis.id,
            "record_id": record.id,
            "sensor": diagnosis.sensor,
            "baseline": diagnosis.baseline,
            "measurement_job_ids": extra_jobs,
            "what": f"diagnosis {diagnosis.id} of record {record.id} (v{record.version})",
        }
        loop = asyncio.get_running_loop()
        try:
            model_doc = await loop.run_in_executor(
                self._executor(),
                fit_adopted,
                cols,
                effects,
                diagnosis.sensor,
                state["bench"],
                source,
                origin,
                have,
                tuple(state.get("added_effects", [])),
                worm_axes_of(summary.get("adoption") or []),
            )
        except NothingToAdopt as exc:
            raise ConflictError(str(exc)) from None
        except InputError as exc:  # a diagnosis stored before adoption was decided with it
            raise ConflictError(f"diagnosis {diagnosis_id}: {exc}") from None
        method = get_method("stage", "kinematic")
        model = CalibrationModel.from_json_dict(model_doc, f"diagnosis {diagnosis.id}")
        validation = await asyncio.to_thread(
            self.jobs.validate, record.job_id, n_fit, method, model
        )
        await self._note_adoption(raw, diagnosis, record, model, extra_jobs)
        return await asyncio.to_thread(
            self.store.records.add_record,
            record.device_id,
            "stage",
            "kinematic",
            model_doc,
            operator=actor,
            validation=validation,
            temp_c=record.temp_c,
            job_id=record.job_id,
            reference_standards=record.reference_standards,
            raw_data=raw,
        )

    async def _succeeded(self, diagnosis_id: int) -> tuple[Diagnosis, DiagnosisResult]:
        """The diagnosis and its result; ConflictError (409) unless it finished successfully (only
        such a diagnosis can be adopted)."""
        diagnosis, result = await asyncio.to_thread(
            self.store.diagnoses.get_diagnosis, diagnosis_id
        )
        if result is None or result.state != "succeeded":
            state = "running" if result is None else f"failed ({result.error})"
            raise ConflictError(
                f"diagnosis {diagnosis_id} is {state}: only a finished diagnosis can be adopted"
            )
        return diagnosis, result

    async def _note_adoption(
        self,
        raw: dict[str, object],
        diagnosis: Diagnosis,
        record: CalibrationRecord,
        model: CalibrationModel,
        extra_jobs: list[int],
    ) -> None:
        """What the adopted version's raw data says of where it comes from: the diagnosis, the
        record it was adopted from, the effects added and the measurements (their points' hashes)
        whose points it was fitted on too. The record's own job is kept by the new version's
        job_id, not in its raw data."""
        raw.pop("job_id", None)
        raw.update(
            {
                "diagnosis_id": diagnosis.id,
                "added_effects": model.state.get("added_effects", []),
                "adopted_from_record_id": record.id,
            }
        )
        if extra_jobs:
            raw["measurement_job_ids"] = extra_jobs
            raw["measurement_points_sha256"] = await asyncio.to_thread(
                self.store.points.points_sha256_by_job, extra_jobs
            )

    @staticmethod
    def _adoptable(
        diagnosis_id: int,
        summary: DiagnosisSummary,
        named: list[str],
        sensor: str,
        have: frozenset[str],
    ) -> list[str]:
        """The named effects the record can adopt, as the diagnosis decided; ConflictError (409)
        with the reason when there is none."""
        verdicts = summary.get("adoption")
        # a diagnosis stored before adoption was decided with it: the named effects as they are
        if verdicts is None:
            return _effects_to_add(named, sensor, have)
        ok = [str(verdict["effect"]) for verdict in verdicts if verdict.get("adoptable")]
        if ok:
            return ok
        blocked = _blocked(verdicts, have)
        if not blocked:
            _effects_to_add(named, sensor, have)
            raise ConflictError(
                f"diagnosis {diagnosis_id} named nothing the record can adopt: there is nothing to "
                "adopt"
            )
        raise ConflictError(
            f"diagnosis {diagnosis_id} named {', '.join(verdict['effect'] for verdict in blocked)}"
            f", which the record cannot adopt from these points: {_why_blocked(blocked)}"
        )

    @staticmethod
    def _chosen(
        diagnosis_id: int,
        summary: DiagnosisSummary,
        named: list[str],
        adoptable: list[str],
        chosen: list[str],
    ) -> list[str]:
        """The chosen effects, each one the diagnosis named and found adoptable; ConflictError (409)
        naming the first that is not, and why."""
        for effect in chosen:
            if effect not in named:
                raise ConflictError(
                    f"diagnosis {diagnosis_id} did not name {effect} (it named "
                    f"{', '.join(named) or 'nothing'}): only a named effect can be adopted"
                )
            if effect not in adoptable:
                raise ConflictError(
                    f"diagnosis {diagnosis_id} named {effect} but did not find it adoptable from "
                    f"these points{_why_not_adoptable(summary, effect)}"
                )
        return [name for name in adoptable if name in chosen]

    async def wait(self, diagnosis_id: int) -> None:
        run = self.running.get(diagnosis_id)
        if run is not None and run.task is not None:
            await asyncio.shield(run.task)

    async def shutdown(self) -> None:
        """Cancel what runs and end the worker processes (a worker busy with a diagnosis would
        otherwise go on, and then wait for ever to hand its result to a daemon that is gone)."""
        for run in list(self.running.values()):
            if run.task is not None:
                run.task.cancel()
        pool, self._pool = self._pool, None
        if pool is None:
            return
        # the executor offers no other way to reach them
        workers = list(getattr(pool, "_processes", {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for worker in workers:
            with contextlib.suppress(Exception):
                worker.terminate()
        deadline = time.monotonic() + WORKER_END_S
        for worker in workers:
            with contextlib.suppress(Exception):
                await asyncio.to_thread(worker.join, max(0.0, deadline - time.monotonic()))
                if worker.is_alive():
                    worker.kill()
