"""What a job procedure offers the job manager, and the measure -> fit -> validate flow of the
procedures that measure point by point.

A procedure is one object in a module of its own (stage grid, the angle procedures), registered in
`service.jobs.registry`. `plan` checks a request against a bench before anything starts (a
`RequestProblem` names the field) and says which points the job will measure; `run` does the
work and answers the `Outcome` the manager keeps as a record version. The manager owns everything
around it: admission, the bench hold, the job's states, cancel and stop.

Procedures that measure fit points, fit, then measure validation points the fit has not seen
derive from `PointProcedure` and give only how a point is measured, the dataset columns of the
stored points and how a model is validated against them.
"""

from __future__ import annotations

import asyncio
import dataclasses
from abc import ABC, abstractmethod
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Generic, NotRequired, Protocol, TypedDict, TypeVar

import numpy as np
from numpy.typing import NDArray

from service import __version__
from service.bench.readings import OUTLIER_RULE
from service.bench.runtime import BenchRuntime
from service.bench.settled import BLOCK
from service.calibration.adaptive_design import AdaptivePlanJSON
from service.calibration.model import CalibrationModel
from service.calibration.registry import FitOptions, Method, get_method
from service.errors import InputError
from service.instruments.base import AmbientSensor, Reading
from service.jobs.bench_time import BenchTime
from service.jobs.budgets import resolutions_deg
from service.jobs.job_parameters import JobParameters, parameters_of
from service.jobs.requests import CalibrationRequest
from service.storage.models import CalibrationJob, SettledPoint
from service.storage.store import PointsRepo, Store

P = TypeVar("P")
Columns = dict[str, NDArray[np.float64]]


class AmbientCondition(TypedDict):
    """One ambient condition as a record keeps it: its value and standard uncertainty, and where it
    came from (`ambient_sensor`: the mean of its readings, with their range and count; `request`:
    as entered)."""

    value: float
    standard_uncertainty: float
    min: NotRequired[float]
    max: NotRequired[float]
    n_readings: NotRequired[int]
    source: str


class AmbientConditions(TypedDict, total=False):
    """The laboratory's air during a job (°C, % relative humidity), each where it is known."""

    ambient_temperature_c: AmbientCondition
    relative_humidity_pct: AmbientCondition


class JobConditions(AmbientConditions, total=False):
    """What a record keeps of the conditions it was measured under (the record's `conditions`):
    the air, the table's mean temperature (°C), the software and instruments, each sensor's
    resolution (degrees, by role), the bench, how its points were measured. A measurement that
    makes no record keeps none."""

    temp_c_mean: float | None
    software_version: str
    firmware: dict[str, str | None]
    instruments: dict[str, str | None]
    resolution_deg: dict[str, float | None]
    bench: str
    clock_speed: float
    outlier_rule: str
    samples_per_point: int
    settle: dict[str, float]


class AdaptiveJobConditions(JobConditions, total=False):
    """An adaptive job's conditions: its design said too."""

    design: str


class ValidationPoint(TypedDict, total=False):
    """One validation point as a record keeps it (a certificate's validation table): its index
    (turntable: its azimuth), the stage's angles, the error's magnitude (degrees), and per axis or
    quantity the reference's reading (its raw reading beside where read through the record's model
    of the reference's errors), the corrected measurement and its expanded uncertainty."""

    point: int
    azimuth_deg: float
    stage_x_deg: float
    stage_y_deg: float
    error_deg: float
    reference_x_deg: float
    reference_raw_x_deg: float
    measured_x_deg: float
    u_x_deg: float
    reference_y_deg: float
    reference_raw_y_deg: float
    measured_y_deg: float
    u_y_deg: float
    reference_angle_arcsec: float
    measured_angle_arcsec: float
    u_angle_arcsec: float
    reference_theta_deg: float
    measured_theta_deg: float
    u_theta_deg: float


class ValidatedFigures(TypedDict, total=False):
    """A stage correction's figures from its validation (degrees): its expanded uncertainty with the
    validation readings' own noise taken out (null when that noise explains the errors), the errors'
    RMS per axis, the readings' noise, and the share of error components within each point's
    expanded uncertainty (of how many)."""

    validated_expanded_uncertainty_deg: float | None
    validation_rms_axis_deg: float
    validation_reading_u_deg: float
    validated_coverage: float
    validated_components: int


class TopUpRound(TypedDict):
    """An adaptive job's top-up: the points read again, the readings added to each, and the
    predicted expanded uncertainty before it (degrees)."""

    points: int
    readings: int
    predicted_before_deg: float


class TopUp(TypedDict):
    """An adaptive plan's round of top-up readings."""

    top_up: TopUpRound


class RecordValidation(ValidatedFigures, total=False):
    """A record's `validation`: the model against points it was not fitted on (their number, RMS
    and largest error in degrees, null without points; what they were compared with; the coverage
    probability of the points' U; the points), and for stage corrections the predicted expanded
    uncertainty with its fixed part and the validated figures; an adaptive job's design, target,
    plan rounds and reading noise by role."""

    n_points: int
    rms_deg: float | None
    max_deg: float | None
    compared_with: str
    coverage_probability: float
    points: list[ValidationPoint]
    predicted_expanded_uncertainty_deg: float
    fixed_u_deg: float
    design: str
    target_expanded_uncertainty_deg: float
    plan: list[AdaptivePlanJSON | TopUp]
    reading_noise_deg: dict[str, float]


class Phase(StrEnum):
    """What a running job is doing (its progress says which)."""

    HOMING = "homing"
    MEASURING = "measuring"
    FITTING = "fitting"
    VALIDATING = "validating"


@dataclass(frozen=True)
class Plan(Generic[P]):
    """What an admitted request will do: its points, and the instruments it calibrates and reads."""

    fit_points: list[P]
    validation_points: list[P]
    device_role: str  # the instrument calibrated: the job's and the record's device
    read_roles: tuple[str, ...]  # every instrument read at each point (all must have identified)
    # what else the job keeps in its parameters
    extra: JobParameters = dataclasses.field(default_factory=lambda: JobParameters())


@dataclass(frozen=True)
class Outcome:
    """What a finished procedure gives the manager to store as a record version."""

    device_id: int
    kind: str
    # None: a measurement that makes no record (a diagnosis reads its points)
    model: CalibrationModel | None
    validation: RecordValidation
    conditions: JobConditions
    n_fit: int  # the first n_fit points were fitted, the rest validated
    # the bench time the job spent (BenchTime.as_json)
    bench_seconds: dict[str, float] | None = None


@dataclasses.dataclass
class SettleMemory:
    """The shortest block (readings) of the statistical settling test at a job's next point: half
    the block the longest transient so far passed with (service.bench.settled)."""

    block: int = BLOCK


@dataclass(frozen=True)
class JobContext:
    """A running job as a procedure sees it."""

    store: Store
    job: CalibrationJob
    bench: BenchRuntime
    request: CalibrationRequest
    # (points done, points total, phase): stored and announced
    report: Callable[[int, int, Phase], Awaitable[None]]
    # A blocking database call (write or read) in a worker thread, waiting through a database outage
    # (the job shows it waits) and raising DatabaseOutage once it outlasts TILTLAB_DB_OUTAGE_S.
    # Writes given to it must be safe to repeat (service.storage.outage).
    db: Callable[..., Awaitable[Any]]
    # counted by the procedure as it moves, settles, reads
    bench_time: BenchTime = dataclasses.field(default_factory=BenchTime)
    # what the statistical settling test has learnt of the bench's sensors during the job
    settling: SettleMemory = dataclasses.field(default_factory=SettleMemory)

    @property
    def job_id(self) -> int:
        return self.job.id


class Procedure(Protocol):
    """One kind of job. `name` is the request's `procedure`, `kind` the kind of record it makes."""

    @property
    def name(self) -> str: ...

    @property
    def kind(self) -> str: ...

    def plan(self, req: CalibrationRequest, bench: BenchRuntime) -> Plan[Any]: ...

    async def run(self, ctx: JobContext) -> Outcome: ...


def ambient_conditions(
    bench: BenchRuntime, req: CalibrationRequest, since_bench_s: float
) -> AmbientConditions:
    """The laboratory's air during the job: read by the bench's ambient sensor since `since_bench_s`
    (its mean, range and count; u combines the sensor's stated u with the range, as a rectangular
    half-width), else as entered with the request (its value and u)."""
    out: AmbientConditions = {}
    sensor = bench.devices.ambient_sensor()
    readings = (
        [reading for reading in sensor.readings_after(since_bench_s) if reading.status in (None, 0)]
        if sensor is not None
        else []
    )
    temperature = _condition(
        sensor, readings, req, "ambient_temperature_c", "temp_c", "standard_uncertainty_c"
    )
    if temperature is not None:
        out["ambient_temperature_c"] = temperature
    humidity = _condition(
        sensor, readings, req, "relative_humidity_pct", "humidity_pct", "standard_uncertainty_pct"
    )
    if humidity is not None:
        out["relative_humidity_pct"] = humidity
    return out


def _condition(
    sensor: AmbientSensor | None,
    readings: Sequence[Reading],
    req: CalibrationRequest,
    key: str,
    field: str,
    u_sensor: str,
) -> AmbientCondition | None:
    """One ambient condition: as the sensor read it (reading attribute `field`), else as the
    request entered it (`key`), else None."""
    values = [
        value for reading in readings if isinstance(value := getattr(reading, field), int | float)
    ]
    if sensor is not None and values:
        return _as_read(sensor, values, u_sensor)
    return _as_entered(req, key)


def _as_read(sensor: AmbientSensor, values: list[float], u_sensor: str) -> AmbientCondition:
    """One ambient condition as the bench's sensor read it: the mean, range and count of its
    readings, u combining the sensor's stated u (attribute `u_sensor`) with the range as a
    rectangular half-width."""
    lo, hi = min(values), max(values)
    u_combined = float(np.hypot(getattr(sensor, u_sensor), (hi - lo) / 2.0 / np.sqrt(3.0)))
    return {
        "value": float(np.mean(values)),
        "standard_uncertainty": u_combined,
        "min": lo,
        "max": hi,
        "n_readings": len(values),
        "source": "ambient_sensor",
    }


def _as_entered(req: CalibrationRequest, key: str) -> AmbientCondition | None:
    """One ambient condition as the request states it (its value and u); None where it states
    none."""
    entered = getattr(req.conditions, key, None) if req.conditions is not None else None
    if entered is None:
        return None
    return {
        "value": entered.value,
        "standard_uncertainty": entered.standard_uncertainty,
        "source": "request",
    }


def job_conditions(
    bench: BenchRuntime,
    req: CalibrationRequest,
    temps_c: Sequence[float],
    since_bench_s: float | None = None,
) -> JobConditions:
    """What a record keeps of the conditions it was measured under (the ambient ones since
    `since_bench_s`)."""
    ambient = ambient_conditions(
        bench, req, bench.clock.monotonic() if since_bench_s is None else since_bench_s
    )
    return {
        **ambient,
        "temp_c_mean": float(np.mean(temps_c)) if len(temps_c) else None,
        "software_version": __version__,
        "firmware": {
            role: (identity.firmware if identity else None)
            for role, identity in bench.identities.items()
        },
        "instruments": {
            role: (identity.in_words() if identity else None)
            for role, identity in bench.identities.items()
        },
        "resolution_deg": resolutions_deg(bench),
        "bench": bench.name,
        "clock_speed": bench.clock.speed,
        "outlier_rule": OUTLIER_RULE,
        "samples_per_point": req.samples_per_point,
        "settle": req.settle.model_dump(),
    }


def bench_epoch(bench: BenchRuntime) -> Callable[[float], float]:
    """Bench seconds -> POSIX seconds (how samples and settled points are stamped)."""
    epoch = bench.clock.utc().timestamp() - bench.clock.real_seconds(bench.clock.monotonic())
    return lambda bench_s: epoch + bench.clock.real_seconds(bench_s)


class PointProcedure(ABC, Generic[P]):
    """Fit points measured (resuming after those already stored), a fit, validation points measured,
    the model validated against them."""

    name: str
    kind: str
    read_roles: tuple[str, ...]  # the instruments settled and read at every point

    @abstractmethod
    def plan(self, req: CalibrationRequest, bench: BenchRuntime) -> Plan[P]: ...

    @abstractmethod
    def stored_point(self, value: Any) -> P:
        """A point as the job's parameters keep it (JSON) -> as `measure` takes it."""

    @abstractmethod
    async def measure(self, ctx: JobContext, index: int, point: P) -> None:
        """Approach, settle, read and store point `index` (its samples and settled means)."""

    @abstractmethod
    def columns(
        self, job: CalibrationJob, points: Sequence[SettledPoint], *, for_fit: bool
    ) -> Columns:
        """The dataset columns of settled points, as `tiltlab calibrate` reads them."""

    @abstractmethod
    def validation(
        self, method: Method, model: CalibrationModel, cols: Columns
    ) -> RecordValidation:
        """The fitted model against the validation points' columns."""

    def fit_options(self, bench: BenchRuntime) -> FitOptions:
        return FitOptions()

    def fitted(self, model: CalibrationModel, fit_cols: Columns) -> None:
        """What the model keeps of its fit points beyond the fit (a procedure's own)."""

    def temperatures_c(self, fit_cols: Columns, points: Sequence[SettledPoint]) -> list[float]:
        """The temperatures a record's mean temperature is taken over."""
        return [point.temp_c_mean for point in points if point.temp_c_mean is not None]

    async def run(self, ctx: JobContext) -> Outcome:
        job, bench = ctx.job, ctx.bench
        # the ambient sensor's readings count from here (this run of the job)
        began = bench.clock.monotonic()
        fit_pts = [self.stored_point(point) for point in job.parameters["fit_points"]]
        val_pts = [self.stored_point(point) for point in job.parameters["validation_points"]]
        n_fit, total = len(fit_pts), len(fit_pts) + len(val_pts)
        devices = self._devices_started_with(job, bench)
        stored = await ctx.db(ctx.store.points.settled_points, job.id)
        done = set.intersection(
            *(
                {point.point for point in stored if point.device_id == device_id}
                for device_id in devices.values()
            )
        )
        await ctx.report(len(done), total, Phase.MEASURING)
        await self._measure_missing(ctx, fit_pts, 0, done, total, Phase.MEASURING)
        await ctx.report(len(done), total, Phase.FITTING)
        method = get_method(self.kind, job.method)
        fit_cols = await ctx.db(self.stored_columns, ctx.store.points, job, n_fit)
        model = await asyncio.to_thread(method.fit, fit_cols, self.fit_options(bench))
        self.fitted(model, fit_cols)
        await ctx.report(len(done), total, Phase.VALIDATING)
        await self._measure_missing(ctx, val_pts, n_fit, done, total, Phase.VALIDATING)
        points = await ctx.db(ctx.store.points.settled_points, job.id)
        val_cols = self.columns(
            job, [point for point in points if point.point >= n_fit], for_fit=False
        )
        validation = await asyncio.to_thread(self.validation, method, model, val_cols)
        conditions = job_conditions(
            bench, ctx.request, self.temperatures_c(fit_cols, points), began
        )
        return Outcome(
            job.device_id, self.kind, model, validation, conditions, n_fit, ctx.bench_time.as_json()
        )

    def _devices_started_with(
        self, job: CalibrationJob, bench: BenchRuntime
    ) -> dict[str, int | None]:
        """The bench's instruments the job reads, by role; InputError when one is not registered, or
        when they are not those the job started with (a resumed job's points stay one set)."""
        devices = {role: bench.device_ids.get(role) for role in self.read_roles}
        missing = [role for role, device_id in devices.items() if device_id is None]
        if missing:
            raise InputError(f"bench {bench.name!r} has no registered {', '.join(missing)}")
        started_with = parameters_of(job).get("device_ids", {})
        if started_with and started_with != devices:
            raise InputError(
                f"the bench's instruments are not those the job started with ({started_with});"
                " its points cannot be continued with other instruments"
            )
        return devices

    async def _measure_missing(
        self,
        ctx: JobContext,
        points: list[P],
        first_index: int,
        done: set[int],
        total: int,
        phase: Phase,
    ) -> None:
        """The points (numbered from `first_index`) not stored yet, each measured and reported;
        a resumed job goes on from those it stored."""
        for k, point in enumerate(points):
            index = first_index + k
            if index not in done:
                await self.measure(ctx, index, point)
                done.add(index)
                await ctx.report(len(done), total, phase)

    def stored_columns(self, points: PointsRepo, job: CalibrationJob, n_fit: int) -> Columns:
        """Blocking (database): the fit columns of the job's first `n_fit` stored points."""
        return self.columns(
            job,
            [
                settled_point
                for settled_point in points.settled_points(job.id)
                if settled_point.point < n_fit
            ],
            for_fit=True,
        )
