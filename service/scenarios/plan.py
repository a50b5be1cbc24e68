"""The adaptive plan for a simulated bench described by a scenario: its reading noise, resolutions,
stage speed and settling give the planner (service.calibration.adaptive_design) what a bench would
measure."""

from __future__ import annotations

import math

import numpy as np

from service.calibration.adaptive_design import (
    AdaptivePlan,
    BenchNoise,
    BenchTimes,
    nearest_point,
    plan_adaptive,
    spread_points,
)
from service.calibration.validation import stage_validation_points
from service.physics.settling import SIM_STAGE_VELOCITY_PPS, Move, move_transient_deg, settling_of
from service.scenarios.model import StageScenario, axis_values
from service.scenarios.run import effect_set, hardware_of

OUTPUT_RATE_HZ = 25.0  # the simulated sensors' default output rate


def scenario_noise(sc: StageScenario) -> BenchNoise:
    """Each sensor's reading noise (σ, with its resolution's r/√12) and the resolutions' part of a
    corrected tilt."""
    fx = effect_set(sc)
    res = {sensor: fx.get("noise", f"{sensor}_resolution_deg") for sensor in ("meas", "ref")}
    sig = {
        sensor: math.hypot(fx.get("noise", f"{sensor}_sigma_deg"), res[sensor] / math.sqrt(12.0))
        for sensor in ("meas", "ref")
    }
    return BenchNoise(
        sig["meas"],
        sig["ref"],
        math.sqrt(sum((resolution / math.sqrt(12.0)) ** 2 for resolution in res.values())),
    )


def scenario_times(sc: StageScenario, step_deg: float, noise_deg: float) -> BenchTimes:
    """Bench time of a point: the stage's rate, and the time a move of `step_deg` takes to settle
    within the noise (from the scenario's settling, with the statistical test's 1.4 x and three
    blocks of margin)."""
    bench = hardware_of(sc)
    rate = SIM_STAGE_VELOCITY_PPS * min(bench.pulse_x_deg, bench.pulse_y_deg)
    st = settling_of(effect_set(sc))
    t = np.arange(0.0, 60.0, 1.0 / OUTPUT_RATE_HZ)
    tr = move_transient_deg(st, Move(-step_deg / rate, step_deg, step_deg / rate), t)
    above = np.nonzero(np.abs(tr) >= noise_deg)[0]
    below_s = float(t[above[-1] + 1]) if above.size and above[-1] + 1 < t.size else 0.0
    return BenchTimes(
        stage_rate_deg_per_s=rate,
        settle_s=1.4 * below_s + 12 / OUTPUT_RATE_HZ,
        output_rate_hz=OUTPUT_RATE_HZ,
    )


def plan_for_scenario(
    sc: StageScenario,
    target_deg: float,
    start: tuple[float, float] = (0.0, 0.0),
    n_validation: int = 4,
    validation_readings: int = 10,
) -> AdaptivePlan:
    """The plan over the scenario's grid (its range, its points as the candidates), on the route a
    job takes from `start` (where the stage stands): from the spread point nearest it, with
    `n_validation` validation points of `validation_readings` readings on the way, drawn as the job
    draws them."""
    xs, ys = axis_values(sc.grid.x_deg), axis_values(sc.grid.y_deg)
    x_deg, y_deg = (min(xs), max(xs)), (min(ys), max(ys))
    noise = scenario_noise(sc)
    step = max((max(xs) - min(xs)) / max(len(xs) - 1, 1), (max(ys) - min(ys)) / max(len(ys) - 1, 1))
    times = scenario_times(sc, step, min(noise.meas_sigma_deg, noise.ref_sigma_deg))
    plan = plan_adaptive(x_deg, y_deg, len(xs), len(ys), target_deg, noise, times)
    spread = spread_points(x_deg, y_deg, len(xs), len(ys))
    return plan.along(
        start,
        nearest_point(spread, start),
        stage_validation_points(spread, n_validation),
        validation_readings,
    )
