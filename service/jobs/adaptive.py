"""An adaptive stage-grid job: the target expanded uncertainty of the correction in the least bench
time.

1. The first point of the spread grid is read with the request's settle rule and NOISE_READINGS
   readings: its spread is each sensor's reading noise.
2. The plan (service.calibration.adaptive_design) chooses the points and the readings at each from
   that noise; a target the bench cannot reach fails the job naming the best it can.
3. Every other point settles by the statistical test against that noise and is read as planned.
4. The fit; its own covariance gives the predicted expanded U of the correction over the range. If
   it is above the target (the plan's noise was optimistic), the plan's points are read once more,
   as often as the missing information needs; still above, the job fails naming how close it came.
5. The validation points as today (statistically settled, samples_per_point readings each). The
   record states the predicted and the validated figures.
"""

from __future__ import annotations

import asyncio
import math
from typing import Any

import numpy as np

from service.calibration.adaptive_design import (
    CAP_READINGS,
    K_EXPANDED,
    MIN_READINGS,
    PLAN_MARGIN,
    AdaptivePlan,
    BenchNoise,
    BenchTimes,
    TargetUnreachable,
    plan_adaptive,
    predicted_u_of_covariance,
    short_tour,
)
from service.calibration.methods.stage.common import MEAS_NAMES
from service.calibration.model import CalibrationModel
from service.calibration.registry import get_method
from service.errors import InputError
from service.jobs.procedure import JobContext, Outcome, Phase, job_conditions
from service.jobs.stage_grid import SENSORS, StageGrid, measure_stage_point
from service.storage.models import SettledPoint

MIN_TOP_UP = MIN_READINGS
# readings of the first point, whose spread is the reading noise the plan starts from
NOISE_READINGS = 20
# a sensor whose readings do not vary at all (quantised) is taken as this noisy
MIN_NOISE_DEG = 1e-6


def _noise_of(settled: dict[int, dict[str, Any]], devices: dict[str, int]) -> dict[str, float]:
    out = {}
    for role in SENSORS:
        s = settled[devices[role]]
        stds = [v for v in (s["ch_x_std"], s["ch_y_std"]) if v is not None]
        out[role] = max(max(stds, default=0.0), MIN_NOISE_DEG)
    return out


def _range(ctx: JobContext) -> tuple[tuple[float, float], tuple[float, float], int, int]:
    g = ctx.request.grid
    # the request's rule
    assert g is not None and g.x_deg is not None and g.y_deg is not None and g.n_x and g.n_y
    return (
        (float(g.x_deg[0]), float(g.x_deg[1])),
        (float(g.y_deg[0]), float(g.y_deg[1])),
        g.n_x,
        g.n_y,
    )


def _plan(ctx: JobContext, noise: dict[str, float], fixed_u: float, target: float) -> AdaptivePlan:
    x_rng, y_rng, n_x, n_y = _range(ctx)
    bench = ctx.bench
    points_so_far = max(1, len(ctx.job.parameters.get("fit_points", [])))
    settle_s = max(ctx.bench_time.settling / points_so_far, 0.2)
    times = BenchTimes(
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
            BenchNoise(noise["measurement_sensor"], noise["reference_sensor"], fixed_u),
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
    points: list[SettledPoint], meas_device: int, errors_xy: np.ndarray, predicted_u: float
) -> dict[str, Any]:
    """The validation's own figures for the correction: its expanded uncertainty estimated from the
    validation errors with the validation readings' own noise taken out, and the share of errors
    within each point's expanded uncertainty (the predicted U of the correction with the point's
    reading noise added)."""
    by_point: dict[int, list[SettledPoint]] = {}
    for p in points:
        by_point.setdefault(p.point, []).append(p)
    u_read2 = []
    for idx in sorted(by_point):
        rows = by_point[idx]
        per_axis = []
        for axis in ("x", "y"):
            var = 0.0
            for row in rows:
                std = getattr(row, f"ch_{axis}_std")
                var += (std or 0.0) ** 2 / max(row.n_samples or 1, 1)
            per_axis.append(var)
        u_read2.append(per_axis)
    u2 = np.array(u_read2, dtype=float)  # (points, 2)
    e = np.asarray(errors_xy, dtype=float)  # (points, 2)
    if e.size == 0:
        return {}
    excess = float(np.mean(e**2) - np.mean(u2))
    within = np.abs(e) <= K_EXPANDED * np.sqrt((predicted_u / K_EXPANDED) ** 2 + u2)
    # errors within the validation readings' own noise leave the correction's U unresolved, not
    # zero: null
    return {
        "validated_expanded_uncertainty_deg": K_EXPANDED * math.sqrt(excess)
        if excess > 0
        else None,
        "validation_rms_axis_deg": float(np.sqrt(np.mean(e**2))),
        "validation_reading_u_deg": float(np.sqrt(np.mean(u2))),
        "validated_coverage": float(np.mean(within)),
        "validated_components": int(within.size),
    }


async def add_correction_figures(ctx: JobContext, outcome: Outcome) -> Outcome:
    """A grid job's record states the same figures an adaptive one does: the predicted expanded U of
    the correction over the range its points span, and the validated figures against it."""
    if (
        outcome.model is None
        or not outcome.validation.get("points")
        or not all(n in outcome.model.parameters for n in MEAS_NAMES)
    ):
        # a method without the measurement-sensor model (homography, ...) predicts no U this way
        return outcome
    fixed_u = float(outcome.validation.get("fixed_u_deg") or _fixed_u(ctx))
    xs = [float(p[0]) for p in ctx.job.parameters["fit_points"]]
    ys = [float(p[1]) for p in ctx.job.parameters["fit_points"]]
    cov = outcome.model.cov_of(list(MEAS_NAMES))
    if cov is None:
        return outcome
    predicted = predicted_u_of_covariance(
        np.nan_to_num(np.asarray(cov, dtype=float)),
        (min(xs), max(xs)),
        (min(ys), max(ys)),
        fixed_u,
        np.asarray(outcome.model.values(MEAS_NAMES), dtype=float),
    )
    points = await ctx.db(ctx.store.points.settled_points, ctx.job.id)
    val_points = [p for p in points if p.point >= outcome.n_fit]
    errors = np.array(
        [
            [q["measured_x_deg"] - q["reference_x_deg"], q["measured_y_deg"] - q["reference_y_deg"]]
            for q in outcome.validation["points"]
        ],
        dtype=float,
    ).reshape(-1, 2)
    outcome.validation.update(
        {
            "predicted_expanded_uncertainty_deg": predicted,
            "fixed_u_deg": fixed_u,
            **validated_figures(val_points, 0, errors, predicted),
        }
    )
    return outcome


def _fixed_u(ctx: JobContext) -> float:
    """The resolutions' part of every corrected tilt (r/√12 of each sensor), as the record's budget
    states it."""
    from service.jobs.budgets import ROLE_WORDS, resolutions_deg

    return math.sqrt(
        sum(
            (r / math.sqrt(12.0)) ** 2
            for role, r in resolutions_deg(ctx.bench).items()
            if role in ROLE_WORDS and r
        )
    )


async def run_adaptive(proc: StageGrid, ctx: JobContext) -> Outcome:
    job, bench, req = ctx.job, ctx.bench, ctx.request
    began = bench.clock.monotonic()
    target = req.target_expanded_uncertainty_deg
    assert target is not None  # the request's rule
    fixed_u = float(job.parameters.get("adaptive", {}).get("fixed_u_deg", 0.0))
    devices = {r: bench.device_ids[r] for r in SENSORS}
    if any(device is None for device in devices.values()):
        raise InputError(f"bench {bench.name!r} has no registered {' or '.join(SENSORS)}")
    stored = await ctx.db(ctx.store.points.settled_points, job.id)
    if stored:
        raise InputError(
            "an adaptive job chooses its points as it measures; it is not resumed: start a new job"
        )
    spread = [proc.stored_point(p) for p in job.parameters["fit_points"]]
    val_pts = [proc.stored_point(p) for p in job.parameters["validation_points"]]
    total_guess = len(spread) + len(val_pts)
    await ctx.report(0, total_guess, Phase.MEASURING)
    first = spread[0]
    settled = await measure_stage_point(ctx, 0, *first, n=NOISE_READINGS)
    noise = _noise_of(settled, devices)
    plan = _plan(ctx, noise, fixed_u, target)
    measured: list[tuple[float, float]] = [first]
    todo = [(p, n) for p, n in zip(plan.points, plan.readings) if p != first]
    await ctx.report(1, len(plan.points) + len(val_pts), Phase.MEASURING)
    for p, n in todo:
        await measure_stage_point(ctx, len(measured), *p, n=n, noise_deg=noise)
        measured.append(p)
        await ctx.report(len(measured), len(plan.points) + len(val_pts), Phase.MEASURING)
    method = get_method("stage", job.method)
    rounds = [plan.as_json()]
    for attempt in range(2):
        await ctx.report(len(measured), len(measured) + len(val_pts), Phase.FITTING)
        fit_cols = await ctx.db(proc.stored_columns, ctx.store.points, job, len(measured))
        model = await asyncio.to_thread(method.fit, fit_cols, proc.fit_options(bench))
        predicted = _predicted_u(model, ctx, fixed_u)
        if predicted <= target:
            break
        if attempt == 1:
            raise InputError(
                f"target_expanded_uncertainty_deg {target:g} deg not reached: after "
                f"{len(measured)} points the predicted expanded uncertainty of the correction "
                f"over the range is {predicted:.4g} deg ({predicted / target:.2f} x the target); "
                f"the plan's reading noise was {noise['measurement_sensor']:.2g} / "
                f"{noise['reference_sensor']:.2g} deg"
            )
        # the fit sees the points noisier than the plan assumed (the first point's spread scatters,
        # a transient, a model that fits less well): read the plan's points once more, as many times
        # as the missing information needs (the variance falls as 1 / the readings of the same
        # points), in reverse order (shortest travel)
        extra = max(
            MIN_TOP_UP,
            math.ceil(plan.readings[0] * ((predicted / (PLAN_MARGIN * target)) ** 2 - 1.0)),
        )
        extra = min(extra, CAP_READINGS)
        rounds.append(
            {
                "top_up": {
                    "points": len(plan.points),
                    "readings": extra,
                    "predicted_before_deg": predicted,
                }
            }
        )
        for p in reversed(plan.points):
            await measure_stage_point(ctx, len(measured), *p, n=extra, noise_deg=noise)
            measured.append(p)
            await ctx.report(len(measured), len(measured) + len(val_pts), Phase.MEASURING)
    proc.fitted(model, fit_cols)
    n_fit = len(measured)
    await ctx.report(n_fit, n_fit + len(val_pts), Phase.VALIDATING)
    # from where the stage stands after the plan (or its top-up pass), in the order of shortest
    # travel
    for k, p in enumerate(short_tour(measured[-1], val_pts)):
        await measure_stage_point(ctx, n_fit + k, *p, noise_deg=noise)
        await ctx.report(n_fit + k + 1, n_fit + len(val_pts), Phase.VALIDATING)
    points = await ctx.db(ctx.store.points.settled_points, job.id)
    val_points = [p for p in points if p.point >= n_fit]
    val_cols = proc.columns(job, val_points, for_fit=False)
    validation = await asyncio.to_thread(proc.validation, method, model, val_cols)
    errors = np.array(
        [
            [q["measured_x_deg"] - q["reference_x_deg"], q["measured_y_deg"] - q["reference_y_deg"]]
            for q in validation.get("points", [])
        ],
        dtype=float,
    ).reshape(-1, 2)
    validation.update(
        {
            "design": "adaptive",
            "target_expanded_uncertainty_deg": target,
            "predicted_expanded_uncertainty_deg": predicted,
            **validated_figures(val_points, devices["measurement_sensor"], errors, predicted),
            "plan": rounds,
            "reading_noise_deg": noise,
            "fixed_u_deg": fixed_u,
        }
    )
    conditions = job_conditions(bench, req, proc.temperatures_c(fit_cols, points), began)
    conditions["design"] = "adaptive"
    return Outcome(
        job.device_id, proc.kind, model, validation, conditions, n_fit, ctx.bench_time.as_json()
    )
