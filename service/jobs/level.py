"""Closed-loop levelling: stage commands from the active record, move, read the reference sensor
back, and aim again by the remaining error until within tolerance."""

from __future__ import annotations

from typing import Any

import numpy as np

from service.bench.readings import fresh_readings, robust_mean, settle
from service.bench.runtime import BenchRuntime
from service.calibration.registry import LevellingMethod
from service.errors import InputError
from service.jobs.active import ActiveModel

READBACK_SAMPLES = 10


def commands(active: ActiveModel, x_deg: float, y_deg: float) -> tuple[float, float]:
    """Stage angles for a wanted table tilt (InputError beyond the travel or out of reach)."""
    if not isinstance(active.method, LevellingMethod):
        raise InputError(f"method {active.method_name} does not level; levelling needs a stage model")
    try:
        out = active.method.level(active.model, {"target_x_deg": np.array([x_deg]), "target_y_deg": np.array([y_deg])})
    except InputError as exc:  # the method speaks of rows of a targets file; here there is one target
        text = str(exc).replace("target row(s) 1 need ", "target row(s) 1 needs ")
        raise InputError(text.replace("target row(s) 1", f"the target x_deg {x_deg:g}, y_deg {y_deg:g}")) from None
    return float(out["stage_x_deg"][0]), float(out["stage_y_deg"][0])


async def level(bench: BenchRuntime, active: ActiveModel, x_deg: float, y_deg: float, tolerance_deg: float,
                max_iterations: int) -> dict[str, Any]:
    aim_x, aim_y = x_deg, y_deg
    sx, sy = commands(active, aim_x, aim_y)  # refused before anything moves
    achieved = (float("nan"), float("nan"))
    for it in range(1, max_iterations + 1):
        sx, sy = await bench.move_stage(sx, sy)
        t0 = await settle(bench, ("reference_sensor",), tolerance_deg=max(tolerance_deg / 2, 1e-4), window_s=0.3,
                          timeout_s=30.0)
        a = robust_mean(await fresh_readings(bench, "reference_sensor", READBACK_SAMPLES, after_bench_s=t0,
                                             timeout_s=10.0))
        achieved = a.mean[0], a.mean[1]
        ex, ey = x_deg - achieved[0], y_deg - achieved[1]
        if max(abs(ex), abs(ey)) <= tolerance_deg:
            return _answer(achieved, it, (sx, sy), True)
        if it == max_iterations:
            break
        aim_x, aim_y = aim_x + ex, aim_y + ey
        sx, sy = commands(active, aim_x, aim_y)
    return _answer(achieved, max_iterations, (sx, sy), False)


def _answer(achieved: tuple[float, float], iterations: int, stage: tuple[float, float], ok: bool) -> dict[str, Any]:
    return {"achieved": {"x_deg": achieved[0], "y_deg": achieved[1]}, "iterations": iterations,
            "stage": {"x_deg": stage[0], "y_deg": stage[1]}, "within_tolerance": ok,
            "measured_by": "reference sensor, mean of the settled read-back"}
