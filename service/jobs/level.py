"""Closed-loop levelling: stage commands from the active record, move, read the reference sensor
back, and aim again until within tolerance.

Each read-back shows the record's error where the stage stands (a bias that stays) and the stage's
positioning error of that move (repeatability, drawn anew with every move). The next aim corrects
the mean of the offsets seen so far (achieved minus aimed), not the last one alone: chasing the
last move's positioning error would add it to the next move's, doubling its variance, where the
mean leaves σ²(1 + 1/k) after k read-backs.

A record that models the stage's backlash aims for the side the stage will arrive from (each move's
direction from where the stage stands); a record that models the reference sensor's own errors reads
the read-back through them, so `achieved` is the table tilt the record says the reference saw (the
raw mean is kept beside it as `reference_raw`)."""

from __future__ import annotations

from typing import TypedDict

import numpy as np

from service.bench.readings import fresh_readings, robust_mean, settle
from service.bench.runtime import BenchRuntime, StagePose
from service.calibration.methods.stage.reference import extrapolation_note, needs_note, true_reading
from service.calibration.model import CalibrationModel
from service.calibration.registry import LevellingMethod
from service.errors import InputError
from service.jobs.active import ActiveModel
from service.jobs.procedure import bench_epoch

READBACK_SAMPLES = 10


def models_backlash(model: CalibrationModel) -> bool:
    """Whether the record fits the stages' lost motion (so where a move ends depends on its
    direction)."""
    return any(
        name in model.parameters and not model.parameters[name].fixed and model.value(name) != 0.0
        for name in ("backlash.x_deg", "backlash.y_deg")
    )


def next_aim(
    target_deg: tuple[float, float], offsets_deg: list[tuple[float, float]]
) -> tuple[float, float]:
    """The tilt to aim at next: the target less the mean offset (achieved - aimed) of the read-backs
    so far, the record's local error estimated without chasing one move's positioning error."""
    bias = np.mean(np.asarray(offsets_deg, dtype=float), axis=0)
    return target_deg[0] - float(bias[0]), target_deg[1] - float(bias[1])


def _aim(
    active: ActiveModel, x_deg: float, y_deg: float, dir_x: float | None, dir_y: float | None
) -> tuple[float, float]:
    if not isinstance(active.method, LevellingMethod):
        raise InputError(
            f"method {active.method_name} does not level; levelling needs a stage model"
        )
    data = {"target_x_deg": np.array([x_deg]), "target_y_deg": np.array([y_deg])}
    if dir_x is not None and dir_y is not None:
        data |= {"dir_x": np.array([dir_x]), "dir_y": np.array([dir_y])}
    try:
        out = active.method.level(active.model, data)
    # the method speaks of rows of a targets file; here there is one target
    except InputError as exc:
        text = str(exc).replace("target row(s) 1 need ", "target row(s) 1 needs ")
        raise InputError(
            text.replace("target row(s) 1", f"the target x_deg {x_deg:g}, y_deg {y_deg:g}")
        ) from None
    return float(out["stage_x_deg"][0]), float(out["stage_y_deg"][0])


def commands(
    active: ActiveModel, x_deg: float, y_deg: float, pose: StagePose | None = None
) -> tuple[float, float]:
    """Stage angles for a wanted table tilt (InputError beyond the travel or out of reach). With the
    stage's pose and a record that models backlash, the angles for the side each stage will arrive
    from."""
    sx, sy = _aim(active, x_deg, y_deg, None, None)
    if (
        pose is None
        or pose.x_deg is None
        or pose.y_deg is None
        or not models_backlash(active.model)
    ):
        return sx, sy
    for _ in range(3):  # the lag shifts the command, which may turn the direction: settle on one
        dx = _arrival_side(sx, pose.x_deg, pose.dir_x)
        dy = _arrival_side(sy, pose.y_deg, pose.dir_y)
        nx, ny = _aim(active, x_deg, y_deg, dx, dy)
        if (nx, ny) == (sx, sy):
            break
        sx, sy = nx, ny
    return sx, sy


def _arrival_side(command_deg: float, stands_deg: float, last_dir: float) -> float:
    """The side a stage arrives at `command_deg` from: +1 from below, -1 from above, and the side of
    its last move when it stays where it stands."""
    if command_deg > stands_deg:
        return 1.0
    if command_deg < stands_deg:
        return -1.0
    return last_dir


def read_back(
    active: ActiveModel, raw: tuple[float, float], temp_c: float | None, t_s: float
) -> tuple[tuple[float, float], str]:
    """The table tilt a read-back of the reference stands for, and how it was read: through the
    record's model of the reference's own errors when it has one (raw otherwise, or when the model
    needs what the read-back lacks)."""
    errors = active.reference
    if errors is None:
        return raw, "reference sensor, mean of the settled read-back"
    why = needs_note(errors, temp_c is not None, True)
    if why is not None:
        return raw, f"reference sensor, mean of the settled read-back, raw: {why}"
    x, y = true_reading(errors, raw[0], raw[1], temp_c, t_s)
    far = extrapolation_note(errors, t_s)
    return (float(x), float(y)), (
        f"reference sensor, mean of the settled read-back, through record {active.record_id}'s "
        f"model of the reference's own errors ({errors.describe()})" + (f"; {far}" if far else "")
    )


class AxesDeg(TypedDict):
    """A tilt or a stage position, per axis (degrees)."""

    x_deg: float
    y_deg: float


class LevelAnswer(TypedDict):
    """What levelling answers: the tilt achieved (as the reference read it back, through the
    record's model of its errors where it has one) and its raw reading, the iterations, the stage
    position, whether it is within the tolerance, and how it was measured."""

    achieved: AxesDeg
    reference_raw: AxesDeg
    iterations: int
    stage: AxesDeg
    within_tolerance: bool
    measured_by: str


async def level(
    bench: BenchRuntime,
    active: ActiveModel,
    x_deg: float,
    y_deg: float,
    tolerance_deg: float,
    max_iterations: int,
) -> LevelAnswer:
    aim_x, aim_y = x_deg, y_deg
    sx, sy = commands(active, aim_x, aim_y, bench.pose)  # refused before anything moves
    offsets: list[tuple[float, float]] = []  # achieved - aimed, one per read-back
    achieved = raw = (float("nan"), float("nan"))
    how = "reference sensor, mean of the settled read-back"
    to_epoch = bench_epoch(bench)
    for it in range(1, max_iterations + 1):
        sx, sy = await bench.move_stage(sx, sy)
        t0 = await settle(
            bench,
            ("reference_sensor",),
            tolerance_deg=max(tolerance_deg / 2, 1e-4),
            window_s=0.3,
            timeout_s=30.0,
        )
        readback = robust_mean(
            await fresh_readings(
                bench, "reference_sensor", READBACK_SAMPLES, after_bench_s=t0, timeout_s=10.0
            )
        )
        raw = readback.mean[0], readback.mean[1]
        achieved, how = read_back(
            active,
            raw,
            readback.temp_c if readback.temp_c is not None else _temp(bench),
            to_epoch(readback.t_end_s),
        )
        ex, ey = x_deg - achieved[0], y_deg - achieved[1]
        if max(abs(ex), abs(ey)) <= tolerance_deg:
            return _answer(achieved, raw, how, it, (sx, sy), True)
        if it == max_iterations:
            break
        offsets.append((achieved[0] - aim_x, achieved[1] - aim_y))
        aim_x, aim_y = next_aim((x_deg, y_deg), offsets)
        sx, sy = commands(active, aim_x, aim_y, bench.pose)
    return _answer(achieved, raw, how, max_iterations, (sx, sy), False)


def _temp(bench: BenchRuntime) -> float | None:
    """The latest temperature a sensor of the bench gave (the read-back's own readings may carry
    none)."""
    for role in ("reference_sensor", "measurement_sensor"):
        reading = bench.latest(role)
        if reading is not None and reading.temp_c is not None:
            return reading.temp_c
    return None


def _answer(
    achieved: tuple[float, float],
    raw: tuple[float, float],
    how: str,
    iterations: int,
    stage: tuple[float, float],
    ok: bool,
) -> LevelAnswer:
    return {
        "achieved": {"x_deg": achieved[0], "y_deg": achieved[1]},
        "reference_raw": {"x_deg": raw[0], "y_deg": raw[1]},
        "iterations": iterations,
        "stage": {"x_deg": stage[0], "y_deg": stage[1]},
        "within_tolerance": ok,
        "measured_by": how,
    }
