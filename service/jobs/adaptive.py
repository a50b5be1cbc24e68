"""An adaptive stage-grid job: the target expanded uncertainty of the correction in the least bench
time.

1. The point of the spread grid nearest where the stage stands (a job after another starts near
   where that one ended) waits for the request's settle rule, probes the reading noise from
   successive differences, settles by the statistical test against it (the request's rule, a fixed
   tolerance, stops well inside a slow sensor's transient) and is read NOISE_READINGS times: its
   spread is each sensor's reading noise. Once the plan says how often a point is read, the first
   point is read that often (the stage still stands there) and stored.
2. The plan (service.calibration.adaptive_design) chooses the points and the readings at each from
   that noise; a target the bench cannot reach fails the job naming the best it can.
3. Every other point of the plan, on a short tour from the first, settles by the statistical test
   against that noise and is read as planned.
   The validation points are measured on the way (each where it lengthens the tour least: a tour
   of them after the plan's would cross the range again), read as in any job and held, to be
   stored after the fit points.
4. The fit; its own covariance gives the predicted expanded U of the correction over the range. If
   it is above the target (the plan's noise was optimistic), the plan's points are read once more,
   as often as the missing information needs; still above, the job fails naming how close it came.
5. The validation points stored, numbered after the fit points (top-up included), and the
   validation computed as in any job. The record states the predicted and the validated figures.
"""

from __future__ import annotations

import asyncio
import math

import numpy as np
from numpy.typing import NDArray

from service.bench.readings import MIN_NOISE_DEG
from service.bench.runtime import BenchRuntime
from service.calibration.adaptive_design import (
    CAP_READINGS,
    K_EXPANDED,
    MIN_READINGS,
    NOISE_READINGS,
    AdaptivePlan,
    AdaptivePlanJSON,
    BenchNoise,
    BenchTimes,
    TargetUnreachable,
    nearest_point,
    plan_adaptive,
    predicted_u_of_covariance,
)
from service.calibration.methods.stage.base import meas_dof
from service.calibration.methods.stage.common import MEAS_NAMES
from service.calibration.model import CalibrationModel
from service.calibration.registry import get_method
from service.calibration.uncertainty import coverage_factor, welch_satterthwaite
from service.errors import InputError
from service.jobs.job_parameters import parameters_of
from service.jobs.procedure import (
    AdaptiveJobConditions,
    JobContext,
    Outcome,
    Phase,
    RecordValidation,
    TopUp,
    ValidationPoint,
    job_conditions,
)
from service.jobs.stage_grid import (
    SENSORS,
    MeasuredPoint,
    StageGrid,
    measure_stage_point,
    read_more,
    read_stage_point,
    store_stage_point,
)
from service.storage.models import SettledPoint
from service.storage.store.hashing import SettledPointFields

MIN_TOP_UP = MIN_READINGS


def _noise_of(settled: dict[int, SettledPointFields], devices: dict[str, int]) -> dict[str, float]:
    """Each sensor's reading noise, its noisier axis's: the yardstick of the statistical settling
    test, and the figure the record states."""
    out = {}
    for role in SENSORS:
        point = settled[devices[role]]
        stds = [std for std in (point["ch_x_std"], point["ch_y_std"]) if std is not None]
        out[role] = max(max(stds, default=0.0), MIN_NOISE_DEG)
    return out


def _axis_variances(
    settled: dict[int, SettledPointFields], devices: dict[str, int]
) -> tuple[float, float]:
    """One reading's variance of meas − ref on the x and the y axis (the two sensors' spreads):
    what the plan weighs each axis by. Not the noisier axis's for both: of two equal axes, the
    larger of two estimates overstates the noise (by some 18 % in variance with 20 readings) and the
    plan reads that much more than it needs."""
    points = [settled[devices[role]] for role in SENSORS]
    spreads = {
        "x": [point["ch_x_std"] for point in points],
        "y": [point["ch_y_std"] for point in points],
    }
    variances = [
        sum(max(std or 0.0, MIN_NOISE_DEG) ** 2 for std in spreads[axis]) for axis in ("x", "y")
    ]
    return variances[0], variances[1]


def _range(ctx: JobContext) -> tuple[tuple[float, float], tuple[float, float], int, int]:
    grid = ctx.request.grid
    # the request's rule
    assert (
        grid is not None
        and grid.x_deg is not None
        and grid.y_deg is not None
        and grid.n_x
        and grid.n_y
    )
    return (
        (float(grid.x_deg[0]), float(grid.x_deg[1])),
        (float(grid.y_deg[0]), float(grid.y_deg[1])),
        grid.n_x,
        grid.n_y,
    )


def _plan(
    ctx: JobContext,
    noise: dict[str, float],
    axis_variances: tuple[float, float],
    fixed_u: float,
    target: float,
) -> AdaptivePlan:
    x_rng, y_rng, n_x, n_y = _range(ctx)
    bench = ctx.bench
    # what the first point (the only one measured when the plan is made) took to settle: what a
    # stand costs on this bench (a slow sensor's long settling makes a second pass dear)
    settle_s = max(ctx.bench_time.settling, 0.2)
    times = BenchTimes(
        stage_rates_deg_per_s=bench.config.stage_rates_deg_per_s(),
        settle_s=settle_s,
        output_rate_hz=1.0 / max(bench.output_interval_s("measurement_sensor"), 1e-3),
    )
    try:
        return plan_adaptive(
            x_rng,
            y_rng,
            n_x,
            n_y,
            target,
            BenchNoise(
                noise["measurement_sensor"], noise["reference_sensor"], fixed_u, axis_variances
            ),
            times,
        )
    except TargetUnreachable as exc:
        raise InputError(str(exc)) from None


def _predicted_u(model: CalibrationModel, ctx: JobContext, fixed_u: float) -> float:
    x_rng, y_rng, _, _ = _range(ctx)
    cov = model.cov_of(list(MEAS_NAMES))
    if cov is None:
        return math.inf
    return predicted_u_of_covariance(
        np.nan_to_num(np.asarray(cov, dtype=float)),
        x_rng,
        y_rng,
        fixed_u,
        np.asarray(model.values(MEAS_NAMES), dtype=float),
    )


def validated_figures(
    points: list[SettledPoint],
    errors_xy: np.ndarray,
    predicted_u: float,
    correction_dof: float,
) -> RecordValidation:
    """The validation's own figures for the correction (a record validation's ValidatedFigures):
    its expanded uncertainty estimated from the validation errors with the validation readings' own
    noise taken out, and the share of errors within each point's expanded uncertainty.

    A point's expanded uncertainty is the predicted U of the correction combined with the point's
    reading noise (each sensor's variance of its mean, from its own readings), expanded with
    Student's t at the Welch-Satterthwaite degrees of freedom of the two: the fit's covariance has
    `correction_dof`, each sensor's mean n − 1. A fixed k = 2 on a noise estimated from 10 readings
    a sensor covers about 94 %, not the 95 % it states."""
    by_point: dict[int, list[SettledPoint]] = {}
    for point in points:
        by_point.setdefault(point.point, []).append(point)
    errors = np.asarray(errors_xy, dtype=float)  # (points, 2)
    if errors.size == 0:
        return {}
    u_read2, k_point = [], []
    correction_var = (predicted_u / K_EXPANDED) ** 2
    for idx in sorted(by_point):
        var_axes, k_axes = [], []
        for axis in ("x", "y"):
            # (variance of the mean, its degrees of freedom) of each sensor at the point
            means = [
                (
                    (getattr(row, f"ch_{axis}_std") or 0.0) ** 2 / max(row.n_samples, 1),
                    row.n_samples - 1,
                )
                for row in by_point[idx]
            ]
            var = sum(v for v, _ in means)
            dof_eff = welch_satterthwaite(
                [(correction_var, correction_dof), *((v, float(nu)) for v, nu in means if nu >= 1)],
                same_dof_shared=False,
            )
            var_axes.append(var)
            k_axes.append(float(coverage_factor(dof_eff)))
        u_read2.append(var_axes)
        k_point.append(k_axes)
    u2 = np.array(u_read2, dtype=float)  # (points, 2)
    k = np.array(k_point, dtype=float)
    excess = float(np.mean(errors**2) - np.mean(u2))
    within = np.abs(errors) <= k * np.sqrt(correction_var + u2)
    # errors within the validation readings' own noise leave the correction's U unresolved, not
    # zero: null
    return {
        "validated_expanded_uncertainty_deg": K_EXPANDED * math.sqrt(excess)
        if excess > 0
        else None,
        "validation_rms_axis_deg": float(np.sqrt(np.mean(errors**2))),
        "validation_reading_u_deg": float(np.sqrt(np.mean(u2))),
        "validated_coverage": float(np.mean(within)),
        "validated_components": int(within.size),
    }


async def add_correction_figures(ctx: JobContext, outcome: Outcome) -> Outcome:
    """A grid job's record states the same figures an adaptive one does: the predicted expanded U of
    the correction over the range its points span, and the validated figures against it."""
    model = outcome.model
    if model is None or not _predicts_u(model, outcome.validation):
        # a method without the measurement-sensor model (homography, ...) predicts no U this way
        return outcome
    fixed_u = float(outcome.validation.get("fixed_u_deg") or _fixed_u(ctx))
    xs = [float(point[0]) for point in ctx.job.parameters["fit_points"]]
    ys = [float(point[1]) for point in ctx.job.parameters["fit_points"]]
    cov = model.cov_of(list(MEAS_NAMES))
    if cov is None:
        return outcome
    predicted = predicted_u_of_covariance(
        np.nan_to_num(np.asarray(cov, dtype=float)),
        (min(xs), max(xs)),
        (min(ys), max(ys)),
        fixed_u,
        np.asarray(model.values(MEAS_NAMES), dtype=float),
    )
    points = await ctx.db(ctx.store.points.settled_points, ctx.job.id)
    val_points = [point for point in points if point.point >= outcome.n_fit]
    errors = _validation_errors_xy(outcome.validation["points"])
    # in this order: the prediction, then the validated figures
    outcome.validation.update(
        {"predicted_expanded_uncertainty_deg": predicted, "fixed_u_deg": fixed_u}
    )
    outcome.validation.update(validated_figures(val_points, errors, predicted, meas_dof(model)))
    return outcome


def _predicts_u(model: CalibrationModel, validation: RecordValidation) -> bool:
    """Whether a grid job's model and validation give what the predicted U needs: the
    measurement-sensor parameters, and validation points to check it against."""
    return bool(validation.get("points")) and all(name in model.parameters for name in MEAS_NAMES)


def _validation_errors_xy(validation_points: list[ValidationPoint]) -> NDArray[np.float64]:
    """The validation's errors (measured - reference) per point and axis, shaped (points, 2) even
    when there are none."""
    return np.array(
        [
            [
                row["measured_x_deg"] - row["reference_x_deg"],
                row["measured_y_deg"] - row["reference_y_deg"],
            ]
            for row in validation_points
        ],
        dtype=float,
    ).reshape(-1, 2)


def _fixed_u(ctx: JobContext) -> float:
    """The resolutions' part of every corrected tilt (r/√12 of each sensor), as the record's budget
    states it."""
    from service.jobs.budgets import ROLE_WORDS, resolutions_deg

    return math.sqrt(
        sum(
            (resolution / math.sqrt(12.0)) ** 2
            for role, resolution in resolutions_deg(ctx.bench).items()
            if role in ROLE_WORDS and resolution
        )
    )


async def run_adaptive(proc: StageGrid, ctx: JobContext) -> Outcome:
    job, bench, req = ctx.job, ctx.bench, ctx.request
    began = bench.clock.monotonic()
    target = req.target_expanded_uncertainty_deg
    assert target is not None  # the request's rule
    fixed_u = float(parameters_of(job).get("adaptive", {}).get("fixed_u_deg", 0.0))
    devices = _sensor_devices(bench)
    await _refuse_resuming(ctx)
    spread = [proc.stored_point(point) for point in job.parameters["fit_points"]]
    val_pts = [proc.stored_point(point) for point in job.parameters["validation_points"]]
    total_guess = len(spread) + len(val_pts)
    await ctx.report(0, total_guess, Phase.MEASURING)
    stood_at = _pose(bench)
    first = nearest_point(spread, stood_at)
    probe = await read_stage_point(ctx, 0, *first, n=NOISE_READINGS, probe_noise=True)
    noise = _noise_of(probe.settled, devices)
    plan = _plan(ctx, noise, _axis_variances(probe.settled, devices), fixed_u, target).along(
        stood_at or first, first, val_pts, req.samples_per_point
    )
    # read as often as every other point of the plan (the fit weighs point means alike: a point
    # read less would scatter more than the plan assumed), where the stage still stands
    await store_stage_point(ctx, await read_more(ctx, probe, plan.readings[0] - NOISE_READINGS))
    measured, held = await _measure_plan(ctx, plan, noise)
    method = get_method("stage", job.method)
    rounds: list[AdaptivePlanJSON | TopUp] = [plan.as_json()]
    for attempt in range(2):
        await ctx.report(len(measured), len(measured) + len(val_pts), Phase.FITTING)
        fit_cols = await ctx.db(proc.stored_columns, ctx.store.points, job, len(measured))
        model = await asyncio.to_thread(method.fit, fit_cols, proc.fit_options(bench))
        predicted = _predicted_u(model, ctx, fixed_u)
        if predicted <= target:
            break
        if attempt == 1:
            raise InputError(_target_missed(target, len(measured), predicted, noise))
        extra = _top_up_readings(plan, predicted, target)
        rounds.append(
            {
                "top_up": {
                    "points": len(plan.points),
                    "readings": extra,
                    "predicted_before_deg": predicted,
                }
            }
        )
        await _top_up(ctx, measured[: len(plan.points)], measured, extra, noise, len(val_pts))
    proc.fitted(model, fit_cols)
    n_fit = len(measured)
    await _store_validation(ctx, held, n_fit)
    points = await ctx.db(ctx.store.points.settled_points, job.id)
    val_points = [point for point in points if point.point >= n_fit]
    val_cols = proc.columns(job, val_points, for_fit=False)
    validation = await asyncio.to_thread(proc.validation, method, model, val_cols)
    errors = _validation_errors_xy(validation.get("points", []))
    # in this order: the design and prediction, the validated figures, the plan
    validation.update(
        {
            "design": "adaptive",
            "target_expanded_uncertainty_deg": target,
            "predicted_expanded_uncertainty_deg": predicted,
        }
    )
    validation.update(validated_figures(val_points, errors, predicted, meas_dof(model)))
    validation.update({"plan": rounds, "reading_noise_deg": noise, "fixed_u_deg": fixed_u})
    conditions: AdaptiveJobConditions = {
        **job_conditions(bench, req, proc.temperatures_c(fit_cols, points), began),
        "design": "adaptive",
    }
    return Outcome(
        job.device_id, proc.kind, model, validation, conditions, n_fit, ctx.bench_time.as_json()
    )


def _pose(bench: BenchRuntime) -> tuple[float, float] | None:
    """Where the stage stands (table tilt, deg); None while that is not known."""
    x_deg, y_deg = bench.pose.x_deg, bench.pose.y_deg
    return None if x_deg is None or y_deg is None else (x_deg, y_deg)


def _sensor_devices(bench: BenchRuntime) -> dict[str, int]:
    """The bench's two sensors by role; InputError when either is not registered."""
    devices = {role: bench.device_ids[role] for role in SENSORS}
    if any(device is None for device in devices.values()):
        raise InputError(f"bench {bench.name!r} has no registered {' or '.join(SENSORS)}")
    return devices


async def _refuse_resuming(ctx: JobContext) -> None:
    """An adaptive job's plan depends on what it measured first, so one with stored points is not
    resumed."""
    stored = await ctx.db(ctx.store.points.settled_points, ctx.job.id)
    if stored:
        raise InputError(
            "an adaptive job chooses its points as it measures; it is not resumed: start a new job"
        )


async def _measure_plan(
    ctx: JobContext, plan: AdaptivePlan, noise: dict[str, float]
) -> tuple[list[tuple[float, float]], list[MeasuredPoint]]:
    """The plan's route after its first point (read already): each fit point read as often as the
    plan says and stored, each validation point on the way statistically settled, read
    samples_per_point times and held. Every fit point measured so far in order, and the validation
    points as measured."""
    measured: list[tuple[float, float]] = [plan.route[0].point]
    held: list[MeasuredPoint] = []
    total = len(plan.route)
    await ctx.report(1, total, Phase.MEASURING)
    for stop in plan.route[1:]:
        if stop.validating:
            # numbered when stored, after the fit points
            held.append(
                await read_stage_point(
                    ctx, total + len(held), *stop.point, n=stop.readings, noise_deg=noise
                )
            )
        else:
            await measure_stage_point(
                ctx, len(measured), *stop.point, n=stop.readings, noise_deg=noise
            )
            measured.append(stop.point)
        await ctx.report(len(measured) + len(held), total, Phase.MEASURING)
    return measured, held


def _target_missed(target: float, n_points: int, predicted: float, noise: dict[str, float]) -> str:
    """Why an adaptive job fails after its top-up pass: how close it came, and the noise the plan
    assumed."""
    return (
        f"target_expanded_uncertainty_deg {target:g} deg not reached: after "
        f"{n_points} points the predicted expanded uncertainty of the correction "
        f"over the range is {predicted:.4g} deg ({predicted / target:.2f} x the target); "
        f"the plan's reading noise was {noise['measurement_sensor']:.2g} / "
        f"{noise['reference_sensor']:.2g} deg"
    )


def _top_up_readings(plan: AdaptivePlan, predicted: float, target: float) -> int:
    """The readings of each plan point in the top-up pass, as many as the missing information
    needs."""
    # the fit sees the points noisier than the plan assumed (the first point's spread scatters,
    # a transient, a model that fits less well): read the plan's points once more, as many times
    # as the missing information needs (the variance falls as 1 / the readings of the same
    # points)
    extra = max(
        MIN_TOP_UP,
        math.ceil(plan.readings[0] * ((predicted / (plan.margin * target)) ** 2 - 1.0)),
    )
    return min(extra, CAP_READINGS)


async def _top_up(
    ctx: JobContext,
    tour: list[tuple[float, float]],
    measured: list[tuple[float, float]],
    readings: int,
    noise: dict[str, float],
    n_validation: int,
) -> None:
    """The plan's points (`tour`, in the order first measured) read once more, `readings` each, in
    reverse order (the stage ends near the last of them), added to `measured`."""
    for point in reversed(tour):
        await measure_stage_point(ctx, len(measured), *point, n=readings, noise_deg=noise)
        measured.append(point)
        await ctx.report(len(measured), len(measured) + n_validation, Phase.MEASURING)


async def _store_validation(ctx: JobContext, held: list[MeasuredPoint], n_fit: int) -> None:
    """The validation points measured on the way, stored in the order measured and numbered after
    the `n_fit` fit points (the record's fit points come first, its validation points after)."""
    await ctx.report(n_fit, n_fit + len(held), Phase.VALIDATING)
    for k, point in enumerate(held):
        await store_stage_point(ctx, point.numbered(n_fit + k))
        await ctx.report(n_fit + k + 1, n_fit + len(held), Phase.VALIDATING)
