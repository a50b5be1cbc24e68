"""Turn a scenario into the rows a bench would have recorded (and the truth behind them)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.io import columns
from service.physics.analog import AnalogSensor, simulate_scale
from service.physics.effects import EffectSet
from service.physics.rotation_axis import RotationBench, simulate_rotation
from service.physics.settling import (
    SIM_STAGE_VELOCITY_PPS,
    moves_along,
    settling_of,
    transient_along_deg,
)
from service.physics.stage import StageBench, simulate_stage
from service.physics.turntable import TurntableInclinometer, simulate_turntable
from service.scenarios.model import (
    Environment,
    RotationScenario,
    ScaleScenario,
    Scenario,
    StageScenario,
    TurntableScenario,
    axis_values,
    effects_dict,
)


@dataclass
class SimulatedRun:
    kind: str
    # what the bench recorded, in dataset order (point indices are integers)
    columns: dict[str, NDArray[Any]]
    truth: dict[str, NDArray[np.float64]] = field(default_factory=dict)  # what it could not record
    bench: Any = None
    effects: EffectSet | None = None


@overload
def hardware_of(scenario: StageScenario) -> StageBench: ...
@overload
def hardware_of(scenario: RotationScenario) -> RotationBench: ...
@overload
def hardware_of(scenario: ScaleScenario) -> AnalogSensor: ...
@overload
def hardware_of(scenario: TurntableScenario) -> TurntableInclinometer: ...
@overload
def hardware_of(
    scenario: Scenario,
) -> StageBench | RotationBench | AnalogSensor | TurntableInclinometer: ...


def hardware_of(
    scenario: Scenario,
) -> StageBench | RotationBench | AnalogSensor | TurntableInclinometer:
    """The physics model of the scenario's fixed hardware (stacked stages, rotary table, ADC sensor
    or turntable)."""
    spec = scenario.bench
    if isinstance(scenario, StageScenario):
        return StageBench(**spec.model_dump())
    if isinstance(scenario, RotationScenario):
        return RotationBench(**spec.model_dump())
    if isinstance(scenario, ScaleScenario):
        fields = spec.model_dump()
        fields.pop("start_arcsec")
        return AnalogSensor(**fields)
    return TurntableInclinometer(
        beta_deg=spec.beta_deg, epsilon_deg=spec.epsilon_deg, m1=spec.m1, m2=spec.m2
    )


def effect_set(scenario: Scenario) -> EffectSet:
    return EffectSet.from_mapping(scenario.kind, effects_dict(scenario))


def temperature(env: Environment, t_s: ArrayLike) -> NDArray[np.float64]:
    t_h = np.asarray(t_s, dtype=float) / 3600.0
    temp: NDArray[np.float64] = (
        env.temp_c
        + env.temp_rate_c_per_h * t_h
        + env.temp_amp_c * np.sin(2 * np.pi * t_h / env.temp_period_h)
    )
    return temp


def move_directions(cmd: NDArray[np.float64], start: float) -> NDArray[np.float64]:
    """Direction of the last move that reached each command (+1/-1); a point not moved to keeps the
    last."""
    prev = np.concatenate([[start], cmd[:-1]])
    steps = np.sign(cmd - prev)
    last = 1.0
    out: NDArray[np.float64] = np.empty_like(steps)
    for i, step in enumerate(steps):
        last = step if step != 0 else last
        out[i] = last
    return out


def stage_sequence(
    scenario: StageScenario, rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Commanded (x, y) in visiting order and each row's grid-point index."""
    xs = np.array(axis_values(scenario.grid.x_deg))
    ys = np.array(axis_values(scenario.grid.y_deg))
    px: list[float] = []
    py: list[float] = []
    pi: list[int] = []
    for j, y in enumerate(ys):
        row = list(range(len(xs)))
        if scenario.grid.order == "serpentine" and j % 2:
            row.reverse()
        for i in row:
            px.append(xs[i])
            py.append(y)
            pi.append(j * len(xs) + i)
    gx, gy, gi = np.array(px), np.array(py), np.array(pi)
    parts = []
    for _ in range(scenario.grid.repeats):
        parts.append(
            rng.permutation(len(gx)) if scenario.grid.order == "random" else np.arange(len(gx))
        )
    order = np.concatenate(parts)
    return gx[order], gy[order], gi[order]


def settling_transient_deg(
    scenario: StageScenario,
    bench: StageBench,
    fx: EffectSet,
    cx: NDArray[np.float64],
    cy: NDArray[np.float64],
    t_s: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Each stage's settling transient at the rows' times: the stage leaves for each point
    `settle_s` before its row is read (as the previous row is read), moving at the simulated
    controller's velocity as the daemon's simulated bench does, so a reading at the same time after
    the same moves is the same offline and on the bench."""
    st = settling_of(fx)
    if st.is_instant:
        return np.zeros_like(cx), np.zeros_like(cy)
    depart = t_s - scenario.grid.settle_s
    out = []
    for cmd, pulse in ((cx, bench.pulse_x_deg), (cy, bench.pulse_y_deg)):
        moves = moves_along(
            cmd.tolist(), -bench.travel_deg, depart.tolist(), SIM_STAGE_VELOCITY_PPS * pulse
        )
        out.append(transient_along_deg(st, moves, t_s))
    return out[0], out[1]


def run_scenario(
    scenario: Scenario, seed: int | None = None, noiseless: bool = False
) -> SimulatedRun:
    rng = np.random.default_rng(scenario.seed if seed is None else seed)
    fx = effect_set(scenario)
    noise_rng = None if noiseless else rng
    if isinstance(scenario, StageScenario):
        return _run_stage(scenario, rng, fx, noise_rng)
    if isinstance(scenario, RotationScenario):
        return _run_rotation(scenario, fx, noise_rng)
    if isinstance(scenario, ScaleScenario):
        return _run_scale(scenario, fx, noise_rng)
    assert isinstance(scenario, TurntableScenario)
    return _run_turntable(scenario, fx, noise_rng)


def _run_stage(
    scenario: StageScenario,
    rng: np.random.Generator,
    fx: EffectSet,
    noise_rng: np.random.Generator | None,
) -> SimulatedRun:
    """The stage grid in visiting order (`rng` draws the order first), each stand read
    readings_per_stand times, the sensors' readings drawn with `noise_rng`."""
    cols: dict[str, NDArray[Any]]
    bench = hardware_of(scenario)
    cx, cy, point = stage_sequence(scenario, rng)
    # The dataset records what the controller executes: whole pulses of this bench.
    cx, cy = bench.quantise(cx, cy)
    dx = move_directions(cx, -bench.travel_deg)
    dy = move_directions(cy, -bench.travel_deg)
    t_s = np.arange(len(cx), dtype=float) * scenario.grid.settle_s
    stand = None
    if (per := scenario.grid.readings_per_stand) > 1:
        # each stand read `per` times while the stage stands: one move, one positioning draw,
        # `per` rows
        k = np.tile(np.arange(per), len(cx))
        t_s = (
            np.arange(len(cx), dtype=float)
            * (scenario.grid.settle_s + (per - 1) * scenario.grid.reading_interval_s)
        ).repeat(per) + k * scenario.grid.reading_interval_s
        cx, cy, point, dx, dy = (np.repeat(column, per) for column in (cx, cy, point, dx, dy))
        stand = np.arange(len(cx)) // per
    temp = temperature(scenario.environment, t_s)
    sx, sy = settling_transient_deg(scenario, bench, fx, cx, cy, t_s)
    sim = simulate_stage(bench, fx, cx + sx, cy + sy, dx, dy, temp, t_s, noise_rng, stand=stand)
    cols = {
        "point": point,
        "stage_x_deg": cx,
        "stage_y_deg": cy,
        "dir_x": dx,
        "dir_y": dy,
        **{k: sim[k] for k in columns.REF + columns.MEAS},
        "temp_c": temp,
        "t_s": t_s,
    }
    truth = {k: sim[k] for k in ("tilt_x_deg", "tilt_y_deg", "actual_x_deg", "actual_y_deg")}
    return SimulatedRun("stage", cols, truth, bench, fx)


def _run_rotation(
    scenario: RotationScenario, fx: EffectSet, noise_rng: np.random.Generator | None
) -> SimulatedRun:
    """The rotation angles of the grid, repeated, read by the triaxial module."""
    rotation_bench = hardware_of(scenario)
    theta = np.tile(np.array(axis_values(scenario.grid.theta_deg)), scenario.grid.repeats)
    sim = simulate_rotation(rotation_bench, fx, theta, noise_rng)
    cols = {
        "point": np.arange(len(theta)) % (len(theta) // scenario.grid.repeats),
        **{k: sim[k] for k in columns.ROTATION_DATASET[1:]},
    }
    return SimulatedRun(
        "rotation", cols, {"theta_true_deg": sim["theta_true_deg"]}, rotation_bench, fx
    )


def _run_scale(
    scenario: ScaleScenario, fx: EffectSet, noise_rng: np.random.Generator | None
) -> SimulatedRun:
    """The reference angles of the grid, repeated, read by the analog sensor behind the ADC."""
    sensor = hardware_of(scenario)
    ref = np.tile(np.array(axis_values(scenario.grid.ref_arcsec)), scenario.grid.repeats)
    temp = np.full(ref.shape, scenario.environment.temp_c)
    sim = simulate_scale(sensor, fx, ref, scenario.bench.start_arcsec, temp, noise_rng)
    cols = {
        "point": np.arange(len(ref)) % (len(ref) // scenario.grid.repeats),
        "ref_arcsec": sim["ref_arcsec"],
        "reading": sim["reading"],
    }
    return SimulatedRun("scale", cols, {"true_ref_arcsec": sim["true_ref_arcsec"]}, sensor, fx)


def _run_turntable(
    scenario: TurntableScenario, fx: EffectSet, noise_rng: np.random.Generator | None
) -> SimulatedRun:
    """Every cycle's pairs at the grid's azimuths, each cycle with its own axis tilt."""
    turntable = hardware_of(scenario)
    az = np.array(axis_values(scenario.grid.azimuth_deg))
    cyc = scenario.grid.cycles
    azimuth = np.tile(az, len(cyc))
    cycle = np.repeat(np.arange(len(cyc)), len(az))
    north = np.repeat([entry.north_arcsec for entry in cyc], len(az))
    east = np.repeat([entry.east_arcsec for entry in cyc], len(az))
    sim = simulate_turntable(
        turntable,
        fx,
        azimuth,
        north,
        east,
        scenario.bench.rotation_deg,
        scenario.grid.pair_interval_s,
        noise_rng,
    )
    cols = {"cycle": cycle, **{k: sim[k] for k in columns.TURNTABLE_DATASET[1:]}}
    truth = {
        "true_north_arcsec": sim["true_north_arcsec"],
        "true_east_arcsec": sim["true_east_arcsec"],
    }
    return SimulatedRun("turntable", cols, truth, turntable, fx)
