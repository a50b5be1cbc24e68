"""The stage-grid procedure: the measurement sensor against the reference sensor over a grid of
stage tilts.

Every point is approached from below on both axes (backlash taken up on one side), both sensors
settle, `samples_per_point` readings of each are averaged after the stated outlier rule, and the
raw samples and the per-point means are stored as they come. The fit is the stage method of
`tiltlab calibrate` with the bench's stage geometry.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.bench.readings import (
    fresh_readings,
    probe_reading_noise,
    robust_mean,
    settle,
    settle_statistical,
)
from service.bench.runtime import BenchRuntime, StageNotHomed
from service.calibration.methods.stage import reference
from service.calibration.model import CalibrationModel, table_tilt_range
from service.calibration.registry import FitOptions, Method, get_method
from service.calibration.uncertainty import COVERAGE
from service.calibration.validation import stage_validation_points
from service.errors import InputError
from service.instruments.base import Reading
from service.instruments.transport import DeviceError
from service.jobs.grid_checks import check_stage_grid
from service.jobs.points import store_point
from service.jobs.procedure import (
    Columns,
    JobContext,
    Outcome,
    Phase,
    Plan,
    PointProcedure,
    RecordValidation,
    ValidationPoint,
    bench_epoch,
)
from service.jobs.requests import CalibrationRequest, Grid, RequestProblem
from service.physics.stage import StageBench
from service.storage.models import CalibrationJob, SettledPoint
from service.storage.samples import Sample
from service.storage.store.hashing import SettledPointFields

log = logging.getLogger("tiltlab.jobs")

# candidate points an adaptive plan chooses among (the planner holds a Jacobian of each)
MAX_CANDIDATES = 41 * 41
APPROACH_DEG = 0.1  # every point is approached from this far below on both axes
SENSORS = ("reference_sensor", "measurement_sensor")
# readings whose successive differences give the noise a point without one settles against
NOISE_PROBE_READINGS = 20

StagePoint = tuple[float, float]


def _tilt(value: float | None) -> float:
    """A sensor reading's angle; an inclinometer reading always has both."""
    if value is None:
        raise DeviceError("an inclinometer reading came without its angle")
    return value


async def _home_stage(ctx: JobContext) -> None:
    """The controller refused a move as "not homed" (after power-up): home the stage, then go on."""
    log.info("job %s: the stage of %s is not homed; homing it", ctx.job_id, ctx.bench.name)
    job = await ctx.db(ctx.store.jobs.get_job, ctx.job_id)
    done, total = job.points_done or 0, job.points_total or 0
    await ctx.report(done, total, Phase.HOMING)
    await ctx.bench.home_stage()
    await ctx.report(
        done, total, Phase(job.phase) if job.phase in tuple(Phase) else Phase.MEASURING
    )


def stage_columns(
    points_ref: Sequence[SettledPoint], points_meas: Sequence[SettledPoint]
) -> Columns:
    """The dataset columns of a job's settled points (reference and measurement rows by point)."""
    meas = {point.point: point for point in points_meas}
    rows = [
        (ref_point, meas[ref_point.point]) for ref_point in points_ref if ref_point.point in meas
    ]

    def col(value_of: Callable[[SettledPoint, SettledPoint], Any]) -> NDArray[np.float64]:
        return np.array(
            [value_of(ref_point, meas_point) for ref_point, meas_point in rows], dtype=float
        )

    return {
        "point": col(lambda r, m: r.point),
        "stage_x_deg": col(lambda r, m: r.cmd_x_deg),
        "stage_y_deg": col(lambda r, m: r.cmd_y_deg),
        "dir_x": col(lambda r, m: 1.0),
        "dir_y": col(lambda r, m: 1.0),
        "ref_x_deg": col(lambda r, m: r.ch_x_mean),
        "ref_y_deg": col(lambda r, m: r.ch_y_mean),
        "meas_x_deg": col(lambda r, m: m.ch_x_mean),
        "meas_y_deg": col(lambda r, m: m.ch_y_mean),
        "temp_c": col(lambda r, m: m.temp_c_mean if m.temp_c_mean is not None else np.nan),
        "t_s": col(lambda r, m: r.t_end_s),
    }


def stage_fit_columns(
    points_ref: Sequence[SettledPoint], points_meas: Sequence[SettledPoint]
) -> Columns:
    """The columns a stage record is fitted on: `stage_columns`, less a temperature column some
    point lacks (the same columns the points CSV carries)."""
    cols = stage_columns(points_ref, points_meas)
    if np.isfinite(cols["temp_c"]).all():
        return cols
    return {name: values for name, values in cols.items() if name != "temp_c"}


def stage_fit_options(stage_bench: StageBench, source: str) -> FitOptions:
    """What a stage fit is told of the bench: its stacked stages' hardware and where that came
    from."""
    return FitOptions(extra={"bench": stage_bench, "bench_source": source})


def _adaptive_spread(grid: Grid) -> list[StagePoint]:
    """An adaptive job's first points: the spread grid over the lattice of candidate points (the
    plan chooses among the rest once the first point's noise is known)."""
    from service.calibration.adaptive_design import spread_points

    # the request's validator requires them
    assert grid.x_deg is not None and grid.y_deg is not None and grid.n_x and grid.n_y
    if grid.n_x * grid.n_y > MAX_CANDIDATES:
        raise RequestProblem(
            "grid",
            f"design adaptive chooses among at most {MAX_CANDIDATES} candidate points; "
            f"n_x x n_y is {grid.n_x * grid.n_y}",
        )
    return spread_points(
        (grid.x_deg[0], grid.x_deg[1]), (grid.y_deg[0], grid.y_deg[1]), grid.n_x, grid.n_y
    )


def _check_travel(grid: Grid, points: list[StagePoint], travel: float) -> None:
    """Every point within the stage's travel; RequestProblem names the first one outside, and the
    field that put it there."""
    for i, (x, y) in enumerate(points):
        if abs(x) > travel or abs(y) > travel:
            field = (
                "grid.points"
                if grid.points is not None
                else "grid.x_deg"
                if abs(x) > travel
                else "grid.y_deg"
            )
            raise RequestProblem(
                field,
                f"point {i} ({x:g}, {y:g}) deg is outside the stage travel of ±{travel:g} deg",
            )


class StageGrid(PointProcedure[StagePoint]):
    name = "stage-grid"
    kind = "stage"
    read_roles = SENSORS

    def plan(self, req: CalibrationRequest, bench: BenchRuntime) -> Plan[StagePoint]:
        if bench.kind != "stage":
            raise RequestProblem(
                "bench", f"{bench.name!r} is a {bench.kind} bench; stage-grid needs a stage bench"
            )
        try:
            get_method("stage", req.method)
        except InputError as exc:
            raise RequestProblem("method", str(exc)) from None
        if req.grid is None or req.grid.is_angles():
            raise RequestProblem(
                "grid",
                "a stage-grid job needs a stage grid: grid.x_deg, grid.y_deg, grid.n_x and "
                "grid.n_y, or grid.points (angles are for the scale and rotation procedures)",
            )
        points = req.grid.stage_points()
        if req.design == "adaptive" and req.method != "kinematic":
            raise RequestProblem(
                "method",
                "design adaptive plans for the kinematic method's measurement-sensor model "
                "(its covariance predicts the correction's uncertainty); use method kinematic",
            )
        # the lattice gives the range and the candidates; the spread grid starts it
        if req.design == "adaptive":
            points = _adaptive_spread(req.grid)
        _check_travel(req.grid, points, bench.config.stage_bench().travel_deg)
        check_stage_grid(
            req.method, req.grid, points, bench.config.stage_bench(), self.fit_options(bench)
        )
        val = stage_validation_points(points, req.validation.n_points)
        return Plan(points, val, "measurement_sensor", SENSORS)

    def stored_point(self, value: Any) -> StagePoint:
        x, y = value
        return float(x), float(y)

    async def measure(self, ctx: JobContext, index: int, point: StagePoint) -> None:
        x, y = point
        await measure_stage_point(ctx, index, x, y)

    async def run(self, ctx: JobContext) -> Outcome:
        if ctx.request.design == "adaptive":
            from service.jobs.adaptive import run_adaptive

            return await run_adaptive(self, ctx)
        from service.jobs.adaptive import add_correction_figures

        return await add_correction_figures(ctx, await super().run(ctx))

    def fit_options(self, bench: BenchRuntime) -> FitOptions:
        return stage_fit_options(bench.config.stage_bench(), f"bench configuration {bench.name}")

    def fitted(self, model: CalibrationModel, fit_cols: Columns) -> None:
        # the calibrated range, kept with the record
        model.fit["table_tilt_range_deg"] = table_tilt_range(fit_cols)

    def temperatures_c(self, fit_cols: Columns, points: Sequence[SettledPoint]) -> list[float]:
        return [float(t) for t in fit_cols.get("temp_c", [])]

    def columns(
        self, job: CalibrationJob, points: Sequence[SettledPoint], *, for_fit: bool
    ) -> Columns:
        meas = [point for point in points if point.device_id == job.device_id]
        ref = [point for point in points if point.device_id != job.device_id]
        return stage_fit_columns(ref, meas) if for_fit else stage_columns(ref, meas)

    def validation(
        self, method: Method, model: CalibrationModel, cols: Columns
    ) -> RecordValidation:
        return stage_validation(method, model, cols)


@dataclass(frozen=True)
class MeasuredPoint:
    """A stage point's raw samples and each device's settled means, as stored under its index."""

    index: int
    samples: list[Sample]
    settled: dict[int, SettledPointFields]
    # what they were made from: each sensor's readings (SENSORS' order) and the stage's command
    readings: tuple[list[Reading], ...]
    command_deg: tuple[float, float]

    def numbered(self, index: int) -> MeasuredPoint:
        """The same point stored under another index (a point measured on the way, numbered when
        it is stored)."""
        return MeasuredPoint(
            index,
            [sample._replace(point=index) for sample in self.samples],
            {device: {**fields, "point": index} for device, fields in self.settled.items()},
            self.readings,
            self.command_deg,
        )


async def measure_stage_point(
    ctx: JobContext,
    index: int,
    x: float,
    y: float,
    dir_x: float = 1.0,
    dir_y: float = 1.0,
    *,
    n: int | None = None,
    noise_deg: dict[str, float] | None = None,
    probe_noise: bool = False,
) -> dict[int, SettledPointFields]:
    """Approach a stage point from the given side of each stage (+1 from below, -1 from above),
    settle both sensors, read, and store the point's samples and settled means (returned by device
    id). `n` readings (the request's samples_per_point by default); with `noise_deg` (each role's
    reading noise) settling ends by the statistical test, else by the request's settle rule, and
    with `probe_noise` then by the statistical test against the noise probed once that rule passed
    (a point that must settle properly before any noise is known)."""
    point = await read_stage_point(
        ctx, index, x, y, dir_x, dir_y, n=n, noise_deg=noise_deg, probe_noise=probe_noise
    )
    await store_stage_point(ctx, point)
    return point.settled


async def _settle_statistically(
    ctx: JobContext,
    noise_deg: dict[str, float],
    *,
    since_bench_s: float | None,
    block: int | None = None,
) -> float:
    """The statistical settling test at a point, its blocks at least the job's `settling.block`
    (or `block`, if longer), which it then raises to half the block this point passed with where
    its transient asked for longer blocks than that (a block imposed here says nothing of the
    sensor)."""
    shortest = max(ctx.settling.block, block or 0)
    settled = await settle_statistical(
        ctx.bench,
        SENSORS,
        noise_deg,
        timeout_s=ctx.request.settle.timeout_s,
        since_bench_s=since_bench_s,
        block=shortest,
    )
    if settled.block > shortest:
        ctx.settling.block = max(ctx.settling.block, settled.block // 2)
    return settled.bench_s


def _read_timeout(bench: BenchRuntime, n: int) -> float:
    """Bench seconds `n` readings of a sensor may need: 20 output intervals each, 5 s at least."""
    return max(5.0, 20 * n * max(bench.output_interval_s(role) for role in SENSORS))


async def store_stage_point(ctx: JobContext, point: MeasuredPoint) -> None:
    """A measured point's samples and settled means, stored whole under its index."""
    await ctx.db(store_point, ctx.store, ctx.job_id, point.index, point.samples, point.settled)


async def read_stage_point(
    ctx: JobContext,
    index: int,
    x: float,
    y: float,
    dir_x: float = 1.0,
    dir_y: float = 1.0,
    *,
    n: int | None = None,
    noise_deg: dict[str, float] | None = None,
    probe_noise: bool = False,
) -> MeasuredPoint:
    """`measure_stage_point` without the storing: the point as it would be stored under `index`."""
    bench, req = ctx.bench, ctx.request
    travel = bench.config.stage_bench().travel_deg
    approach = (
        min(max(x - dir_x * APPROACH_DEG, -travel), travel),
        min(max(y - dir_y * APPROACH_DEG, -travel), travel),
    )
    clock = bench.clock
    began = clock.monotonic()
    try:
        await bench.move_stage(*approach, passing=True)
    except StageNotHomed:
        await _home_stage(ctx)
        await bench.move_stage(*approach, passing=True)
    cx, cy = await bench.move_stage(x, y)
    # moving ends when the stage stopped (between the controller's last "moving" and first "ready"
    # answers), not when the daemon got round to reading them (on a loaded machine running a
    # sped-up bench, that latency would count as bench seconds of moving)
    stood = bench.stopped_bench_s
    if noise_deg is not None:
        t0 = await _settle_statistically(ctx, noise_deg, since_bench_s=None)
    else:
        t0 = await settle(
            bench,
            SENSORS,
            tolerance_deg=req.settle.tolerance_deg,
            window_s=req.settle.window_s,
            timeout_s=req.settle.timeout_s,
            since_bench_s=bench.stopped_after(began),
        )
        if probe_noise:
            probed = await probe_reading_noise(
                bench,
                SENSORS,
                NOISE_PROBE_READINGS,
                after_bench_s=t0,
                timeout_s=_read_timeout(bench, NOISE_PROBE_READINGS),
            )
            # nothing learnt yet of how slow this sensor is, and the move may have been short (the
            # stage stood at or near the point: a small, slow transient that blocks of a few
            # readings do not see move): blocks as long as the request's settle window
            window = math.ceil(
                req.settle.window_s / max(bench.output_interval_s(role) for role in SENSORS)
            )
            t0 = await _settle_statistically(ctx, probed, since_bench_s=stood, block=window)
    n = req.samples_per_point if n is None else n
    timeout = _read_timeout(bench, n)
    got = await asyncio.gather(
        *(fresh_readings(bench, role, n, after_bench_s=t0, timeout_s=timeout) for role in SENSORS)
    )
    ctx.bench_time.add(
        moving=stood - began,
        settling=t0 - stood,
        reading=max(reading.bench_s for readings in got for reading in readings) - t0,
    )
    return _point_of(ctx, index, (cx, cy), tuple(got))


async def read_more(ctx: JobContext, point: MeasuredPoint, n: int) -> MeasuredPoint:
    """`point` with `n` more readings of each sensor, taken where the stage still stands (the
    readings that follow its last ones): a point read before the job knew how often to read it."""
    if n <= 0:
        return point
    bench = ctx.bench
    last = max(reading.bench_s for readings in point.readings for reading in readings)
    more = await asyncio.gather(
        *(
            fresh_readings(bench, role, n, after_bench_s=last, timeout_s=_read_timeout(bench, n))
            for role in SENSORS
        )
    )
    newest = max(reading.bench_s for readings in more for reading in readings)
    ctx.bench_time.add(reading=newest - last)
    return _point_of(
        ctx,
        point.index,
        point.command_deg,
        tuple(old + new for old, new in zip(point.readings, more, strict=True)),
    )


def _point_of(
    ctx: JobContext, index: int, command_deg: tuple[float, float], got: tuple[list[Reading], ...]
) -> MeasuredPoint:
    """The point as stored under `index`: each sensor's raw samples and settled means."""
    bench = ctx.bench
    cx, cy = command_deg
    to_epoch = bench_epoch(bench)
    rows: list[Sample] = []
    settled: dict[int, SettledPointFields] = {}
    for role, readings in zip(SENSORS, got):
        dev = bench.device_ids[role]
        rows += [
            Sample(
                dev,
                to_epoch(reading.bench_s),
                _tilt(reading.x_deg),
                _tilt(reading.y_deg),
                None,
                reading.temp_c,
                ctx.job_id,
                index,
                "calibration",
            )
            for reading in readings
        ]
        averaged = robust_mean(readings)
        settled[dev] = {
            "point": index,
            "cmd_x_deg": cx,
            "cmd_y_deg": cy,
            "n_samples": averaged.n_used,
            "t_start_s": to_epoch(averaged.t_start_s),
            "t_end_s": to_epoch(averaged.t_end_s),
            "ch_x_mean": averaged.mean[0],
            "ch_y_mean": averaged.mean[1],
            "ch_z_mean": None,
            "ch_x_std": averaged.std[0],
            "ch_y_std": averaged.std[1],
            "ch_z_std": None,
            "temp_c_mean": averaged.temp_c,
        }
    return MeasuredPoint(index, rows, settled, got, command_deg)


def stage_validation(method: Method, model: CalibrationModel, cols: Columns) -> RecordValidation:
    """A stage model against validation points: the corrected measurement sensor against the
    reference, read through what the record knows of the reference's own errors (the raw reference
    kept beside)."""
    if cols["point"].size == 0:
        return {"n_points": 0, "rms_deg": None, "max_deg": None}
    out = method.correct(model, cols)
    ref_x, ref_y, how = reference_at_points(model, cols)
    err = np.hypot(out["tilt_x_deg"] - ref_x, out["tilt_y_deg"] - ref_y)
    return {
        "n_points": int(err.size),
        "rms_deg": float(np.sqrt(np.mean(err**2))),
        "max_deg": float(err.max()),
        "compared_with": how,
        # the coverage probability of the points' expanded uncertainties u_x_deg/u_y_deg
        "coverage_probability": COVERAGE,
        "points": [
            _validation_point(cols, out, (ref_x, ref_y), i, float(err[i])) for i in range(err.size)
        ],
    }


def reference_at_points(
    model: CalibrationModel, cols: Columns
) -> tuple[NDArray[np.float64], NDArray[np.float64], str]:
    """The table tilt the reference reads at stored points: its readings, through the record's model
    of its own errors when it has one; and how, in words."""
    errors = reference.reference_errors(model)
    if errors is None:
        return (
            cols["ref_x_deg"],
            cols["ref_y_deg"],
            "reference sensor reading at each validation point",
        )
    x, y = reference.true_reading(
        errors, cols["ref_x_deg"], cols["ref_y_deg"], cols.get("temp_c"), cols.get("t_s")
    )
    how = (
        "reference sensor reading at each validation point, through the record's model of the "
        f"reference's own errors ({errors.describe()})"
    )
    lacking = ~(np.isfinite(x) & np.isfinite(y))
    if lacking.any():  # a point without the temperature the model needs: its raw reading, said so
        x, y = np.where(lacking, cols["ref_x_deg"], x), np.where(lacking, cols["ref_y_deg"], y)
        how += f"; raw at {int(lacking.sum())} point(s) read without a temperature"
    return x, y, how


def _validation_point(
    cols: Columns,
    out: dict[str, NDArray[np.float64]],
    reference_deg: tuple[NDArray[np.float64], NDArray[np.float64]],
    i: int,
    error_deg: float,
) -> ValidationPoint:
    """One validation point: the reference sensor's reading (through the record's model of its own
    errors, the raw reading beside when that differs), the corrected measurement and its expanded
    uncertainty per axis (what a certificate's validation table shows), and the error's
    magnitude."""
    point: ValidationPoint = {
        "point": int(cols["point"][i]),
        "stage_x_deg": float(cols["stage_x_deg"][i]),
        "stage_y_deg": float(cols["stage_y_deg"][i]),
        "error_deg": error_deg,
        "reference_x_deg": float(reference_deg[0][i]),
    }
    if reference_deg[0] is not cols["ref_x_deg"]:
        point["reference_raw_x_deg"] = float(cols["ref_x_deg"][i])
    point["measured_x_deg"] = float(out["tilt_x_deg"][i])
    if "u_tilt_x_deg" in out:
        point["u_x_deg"] = float(out["u_tilt_x_deg"][i])
    point["reference_y_deg"] = float(reference_deg[1][i])
    if reference_deg[1] is not cols["ref_y_deg"]:
        point["reference_raw_y_deg"] = float(cols["ref_y_deg"][i])
    point["measured_y_deg"] = float(out["tilt_y_deg"][i])
    if "u_tilt_y_deg" in out:
        point["u_y_deg"] = float(out["u_tilt_y_deg"][i])
    return point


STAGE_GRID = StageGrid()
