"""The adaptive plan for a simulated bench described by a scenario: its reading noise, resolutions,
stage speed and settling give the planner (service.calibration.adaptive_design) what a bench would
measure."""

from __future__ import annotations

import math
from dataclasses import dataclass

from service.calibration.adaptive_design import (
    PLAN_MARGINS,
    AdaptivePlan,
    BenchNoise,
    BenchTimes,
    nearest_point,
    plan_adaptive,
    spread_points,
)
from service.calibration.validation import stage_validation_points
from service.physics.settling import (
    SIM_STAGE_VELOCITY_PPS,
    mean_settled_within_s,
    settled_within_s,
    settling_of,
)
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


def stage_rates_deg_per_s(sc: StageScenario) -> tuple[float, float]:
    """How fast each simulated stage tilts the table (x, y)."""
    bench = hardware_of(sc)
    return (SIM_STAGE_VELOCITY_PPS * bench.pulse_x_deg, SIM_STAGE_VELOCITY_PPS * bench.pulse_y_deg)


def scenario_times(sc: StageScenario, step_deg: float, noise_deg: float) -> BenchTimes:
    """Bench time of a point: each stage's rate, and the time a move of `step_deg` on the slower
    stage takes to settle within the noise (from the scenario's settling, with the statistical
    test's 1.4 x and three blocks of margin)."""
    rates = stage_rates_deg_per_s(sc)
    st = settling_of(effect_set(sc))
    below_s = settled_within_s(st, step_deg, min(rates), noise_deg, step_s=1.0 / OUTPUT_RATE_HZ)
    return BenchTimes(
        stage_rates_deg_per_s=rates,
        settle_s=1.4 * below_s + 12 / OUTPUT_RATE_HZ,
        output_rate_hz=OUTPUT_RATE_HZ,
    )


def plan_for_scenario(
    sc: StageScenario,
    target_deg: float,
    start: tuple[float, float] = (0.0, 0.0),
    n_validation: int = 4,
    validation_readings: int = 10,
    margins: tuple[float, ...] = PLAN_MARGINS,
) -> AdaptivePlan:
    """The plan over the scenario's grid (its range, its points as the candidates), on the route a
    job takes from `start` (where the stage stands): from the spread point nearest it, with
    `n_validation` validation points of `validation_readings` readings on the way, drawn as the job
    draws them; aimed at the best of `margins` x the target."""
    xs, ys = axis_values(sc.grid.x_deg), axis_values(sc.grid.y_deg)
    x_deg, y_deg = (min(xs), max(xs)), (min(ys), max(ys))
    noise = scenario_noise(sc)
    step = max((max(xs) - min(xs)) / max(len(xs) - 1, 1), (max(ys) - min(ys)) / max(len(ys) - 1, 1))
    times = scenario_times(sc, step, min(noise.meas_sigma_deg, noise.ref_sigma_deg))
    plan = plan_adaptive(x_deg, y_deg, len(xs), len(ys), target_deg, noise, times, margins=margins)
    spread = spread_points(x_deg, y_deg, len(xs), len(ys))
    return plan.along(
        start,
        nearest_point(spread, start),
        stage_validation_points(spread, n_validation),
        validation_readings,
    )


@dataclass(frozen=True)
class DesignFloor:
    """The least bench time the adaptive design can take on a bench (seconds)."""

    moving: float
    settling: float
    reading: float

    @property
    def total(self) -> float:
        return self.moving + self.settling + self.reading


def design_floor(
    sc: StageScenario,
    target_deg: float,
    n_validation: int = 4,
    validation_readings: int = 10,
    mean_share: float | None = None,
) -> DesignFloor:
    """The least bench time of an adaptive job on the scenario's bench, whatever its settling rule
    and however well it knew the noise: its route from its first point (no move to it), each move at
    the stage's rate, each stand settled only until the move's transient stays within one reading's
    noise (the physics of the scenario's settling, per axis: the shorter axis settles while the
    longer still moves), and readings exactly at the target (the plan aimed at 1 x it, no margin
    for a top-up pass).

    With `mean_share`, each stand settles instead until the transient in the mean of its readings
    is within that share of the mean's standard error (σ/√n): the floor of a job whose points'
    means carry no more of the transient than that (one reading's noise at the first reading can
    still bias a long mean by several standard errors on a slow sensor)."""
    xs, ys = axis_values(sc.grid.x_deg), axis_values(sc.grid.y_deg)
    spread = spread_points((min(xs), max(xs)), (min(ys), max(ys)), len(xs), len(ys))
    first = nearest_point(spread, (0.0, 0.0))
    plan = plan_for_scenario(sc, target_deg, first, n_validation, validation_readings, (1.0,))
    st = settling_of(effect_set(sc))
    noise = scenario_noise(sc)
    level = max(noise.meas_sigma_deg, noise.ref_sigma_deg)

    def in_mean(readings: int) -> tuple[float, int]:
        """(level, readings) a stand's transient is held to: one reading within the noise, or
        with `mean_share` the mean of its readings within that share of its standard error."""
        if mean_share is None:
            return level, 1
        return mean_share * level / math.sqrt(readings), readings

    times = plan.times
    moving = settling = reading = 0.0
    here = first
    for stop in plan.route:
        if stop.point != here:
            move_s = times.move_s(here, stop.point)
            moving += move_s
            settling += max(
                0.0,
                *(
                    mean_settled_within_s(
                        st,
                        stop.point[axis] - here[axis],
                        times.stage_rates_deg_per_s[axis],
                        *in_mean(stop.readings),
                        1.0 / times.output_rate_hz,
                    )
                    - (move_s - times.axis_move_s(axis, stop.point[axis] - here[axis]))
                    for axis in (0, 1)
                ),
            )
        reading += stop.readings / times.output_rate_hz
        here = stop.point
    return DesignFloor(moving, settling, reading)
