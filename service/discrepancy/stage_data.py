"""What stage data carry (stage angles, the other axis, approach direction, temperature, time) and
the residual structure tests that locate a disagreement in that covariate space."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.discrepancy import stats
from service.discrepancy.model import Block
from service.physics.stage import StageBench

# Candidate effects of docs/models.md §5 a stage bench model can lack, in a fixed order.
STAGE_CANDIDATES = (
    "offaxis_coupling",
    "backlash",
    "periodic_error",
    "sensor_nonlinearity",
    "temperature_drift",
    "time_drift",
)

# Said beside a candidate the final model barely sees (see workflow.WEAK_SEPARABILITY).
STAGE_SEPARABILITY_HINTS = {
    "time_drift": "a linear drift is told from the bench's geometry (and from a temperature "
    "ramp) only by time that does not follow the stage angles: on one serpentine pass it mostly "
    "does; visiting the points in random order, or repeating the grid, separates them",
    "temperature_drift": "temperature drift is told from geometry and time drift only by "
    "temperature changes that follow neither the stage angles nor the time; the grid repeated "
    "in random order, over a larger temperature swing, separates it",
}

TEMP_MIN_SPAN_K = 0.05  # below this the temperature is treated as constant
TIME_MIN_SPAN_S = 1.0


@dataclass
class StageData:
    """One sensor's readings at the commanded stage points, with the covariates present."""

    sensor: str
    cmd_x_deg: NDArray[np.float64]
    cmd_y_deg: NDArray[np.float64]
    observed: NDArray[np.float64]  # (N, 2): sensor x and y readings, deg
    dir_x: NDArray[np.float64] | None
    dir_y: NDArray[np.float64] | None
    temp_c: NDArray[np.float64] | None
    t_s: NDArray[np.float64] | None
    point: NDArray[np.float64] | None
    bench: StageBench

    @classmethod
    def from_columns(
        cls,
        cols: Mapping[str, NDArray[np.float64]],
        sensor: str = "ref",
        bench: StageBench | None = None,
    ) -> StageData:
        def g(c: str) -> NDArray[np.float64] | None:
            return None if c not in cols else np.asarray(cols[c], dtype=float)

        def req(c: str) -> NDArray[np.float64]:
            return np.asarray(cols[c], dtype=float)

        obs = np.column_stack([req(f"{sensor}_x_deg"), req(f"{sensor}_y_deg")])
        return cls(
            sensor,
            req("stage_x_deg"),
            req("stage_y_deg"),
            obs,
            g("dir_x"),
            g("dir_y"),
            g("temp_c"),
            g("t_s"),
            g("point"),
            bench or StageBench(),
        )

    def __len__(self) -> int:
        return self.cmd_x_deg.size

    def quantised(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The stage angles the controller executes: whole pulses (seed 000 §1)."""
        return self.bench.quantise(self.cmd_x_deg, self.cmd_y_deg)

    def dir(self, axis: str) -> NDArray[np.float64] | None:
        return self.dir_x if axis == "x" else self.dir_y

    def both_directions(self, axis: str) -> bool:
        direction = self.dir(axis)
        return direction is not None and bool(np.any(direction > 0)) and bool(np.any(direction < 0))

    def temp_varies(self) -> bool:
        return self.temp_c is not None and float(np.ptp(self.temp_c)) >= TEMP_MIN_SPAN_K

    def time_varies(self) -> bool:
        return self.t_s is not None and float(np.ptp(self.t_s)) >= TIME_MIN_SPAN_S

    def worm_phase(self, axis: str) -> tuple[NDArray[np.float64], float]:
        """Phase of the worm (rad) at each point and the worm period in output degrees."""
        qx, qy = self.quantised()
        period = self.bench.worm_period_x_deg if axis == "x" else self.bench.worm_period_y_deg
        stage_deg = qx if axis == "x" else qy
        return 2.0 * np.pi * stage_deg / period, period


def sensor_param_names(sensor: str) -> dict[str, tuple[str, ...]]:
    """Registry parameter names of the sensor-side candidates, for the sensor being modelled."""
    return {
        "sensor_nonlinearity": (f"{sensor}_x_per_deg", f"{sensor}_y_per_deg"),
        "temperature_drift": (
            f"{sensor}_x_deg_per_k",
            f"{sensor}_y_deg_per_k",
            f"{sensor}_scale_per_k",
        ),
        "time_drift": (f"{sensor}_x_deg_per_h", f"{sensor}_y_deg_per_h"),
    }


def candidate_block(effect: str, names: Mapping[str, tuple[str, ...]]) -> Block | None:
    """The parameters a candidate adds, the same on every stage baseline; None for one it does not
    know."""
    if effect == "backlash":
        return Block(effect, ("x_deg", "y_deg"), ("deg", "deg"), (0.01, 0.01), (0.0, 0.0))
    if effect == "periodic_error":
        return Block(
            effect,
            ("x_sin_deg", "x_cos_deg", "y_sin_deg", "y_cos_deg"),
            ("deg",) * 4,
            (0.01,) * 4,
            (0.0,) * 4,
        )
    if effect == "sensor_nonlinearity":
        return Block(effect, names[effect], ("1/deg", "1/deg"), (1e-4, 1e-4), (0.0, 0.0))
    if effect == "temperature_drift":
        return Block(
            effect, names[effect], ("deg/K", "deg/K", "1/K"), (1e-3, 1e-3, 1e-4), (0.0,) * 3
        )
    if effect == "time_drift":
        return Block(effect, names[effect], ("deg/h", "deg/h"), (1e-2, 1e-2), (0.0, 0.0))
    return None


def common_skips(data: StageData) -> dict[str, str]:
    """Candidates the data cannot support at all, with the reason in the lab's words."""
    skip: dict[str, str] = {}
    if data.dir_x is None and data.dir_y is None:
        skip["backlash"] = "no dir_x/dir_y columns: the direction of the last move is not recorded"
    elif not (data.both_directions("x") or data.both_directions("y")):
        skip["backlash"] = (
            "a single approach direction per stage: every point was reached moving the same "
            "way, so lost motion is a constant offset the model already has"
        )
    if data.temp_c is None:
        skip["temperature_drift"] = "no temp_c column"
    elif not data.temp_varies():
        skip["temperature_drift"] = (
            f"temperature constant within {np.ptp(data.temp_c):.3g} K "
            f"(at {np.mean(data.temp_c):.2f} °C): a temperature coefficient cannot be "
            "told from a zero offset"
        )
    if data.t_s is None:
        skip["time_drift"] = "no t_s column: the time of each point is not recorded"
    elif not data.time_varies():
        skip["time_drift"] = "all points recorded at the same time (t_s constant)"
    return skip


_SHAPE_TERMS = ("θx²", "θx·θy", "θy²", "θx³", "θx²·θy", "θx·θy²", "θy³")
_SHAPE_WORDS = {
    "θx²": "grows with |θx|, same sign on both sides",
    "θx·θy": "changes sign across the diagonals (twist)",
    "θy²": "grows with |θy|, same sign on both sides",
    "θx³": "grows with |θx| faster than linearly, with the sign of θx",
    "θx²·θy": "grows with |θx| at large |θy|, with the sign of θy",
    "θx·θy²": "grows with |θy| at large |θx|, with the sign of θx",
    "θy³": "grows with |θy| faster than linearly, with the sign of θy",
}


def stage_structure(
    data: StageData, resid: NDArray[np.float64], alpha: float = 0.01
) -> list[stats.StructureTest]:
    """Residual structure tests per axis against every covariate the data carry."""
    x, y = data.cmd_x_deg, data.cmd_y_deg
    scale = max(float(np.max(np.abs(np.concatenate([x, y])))), 1e-9)
    scaled_x, scaled_y = x / scale, y / scale
    terms = np.column_stack(
        [
            scaled_x * scaled_x,
            scaled_x * scaled_y,
            scaled_y * scaled_y,
            scaled_x**3,
            scaled_x * scaled_x * scaled_y,
            scaled_x * scaled_y * scaled_y,
            scaled_y**3,
        ]
    )
    tests: list[stats.StructureTest] = []
    for axis, name in enumerate(("x", "y")):
        resid_axis = resid[:, axis]
        if _shape_testable(data):
            tests.append(_shape_beyond_linear(resid_axis, scaled_x, scaled_y, terms, name))
        tests += _found(
            *_direction_tests(data, resid_axis, name),
            *_drift_tests(data, resid_axis, name),
            *_worm_tests(data, resid_axis, name),
        )
    return stats.mark_significant(tests, alpha)


def _shape_testable(data: StageData) -> bool:
    """Enough rows on enough distinct grid points for the cubic shape terms to mean something."""
    x, y = data.cmd_x_deg, data.cmd_y_deg
    return (
        len(data) >= 12 and np.unique(np.round(np.column_stack([x, y]), 6), axis=0).shape[0] >= 10
    )


def _shape_beyond_linear(
    resid_axis: NDArray[np.float64],
    scaled_x: NDArray[np.float64],
    scaled_y: NDArray[np.float64],
    terms: NDArray[np.float64],
    name: str,
) -> stats.StructureTest:
    """The shape test on what the residual has beyond a plane: the linear part is what any
    baseline fits."""
    plane = np.column_stack([np.ones_like(scaled_x), scaled_x, scaled_y])
    base_resid = resid_axis - plane @ np.linalg.lstsq(plane, resid_axis, rcond=None)[0]
    return stats.shape_test(base_resid, list(_SHAPE_TERMS), terms, name, "deg", _SHAPE_WORDS)


def _direction_tests(
    data: StageData, resid_axis: NDArray[np.float64], name: str
) -> list[stats.StructureTest | None]:
    """Lost motion: a step between the two approach directions, for each stage that has both."""
    tests: list[stats.StructureTest | None] = []
    for stage in ("x", "y"):
        direction = data.dir(stage)
        if direction is not None and data.both_directions(stage):
            tests.append(stats.direction_test(resid_axis, direction, name, stage, "deg"))
    return tests


def _drift_tests(
    data: StageData, resid_axis: NDArray[np.float64], name: str
) -> list[stats.StructureTest | None]:
    """Temperature and time drift: a trend with whichever of the two the data record and vary."""
    tests: list[stats.StructureTest | None] = []
    if data.temp_c is not None and data.temp_varies():
        tests.append(
            stats.correlation_test(
                resid_axis, data.temp_c, name, "temp_c", "temperature", "K", "deg"
            )
        )
    if data.t_s is not None and data.time_varies():
        tests.append(
            stats.correlation_test(resid_axis, data.t_s / 3600.0, name, "t_s", "time", "h", "deg")
        )
        tests.append(stats.runs_test(resid_axis, data.t_s, name))
    return tests


def _worm_tests(
    data: StageData, resid_axis: NDArray[np.float64], name: str
) -> list[stats.StructureTest | None]:
    """Periodic error: an oscillation at each stage's worm period."""
    tests: list[stats.StructureTest | None] = []
    for stage in ("x", "y"):
        phase, period = data.worm_phase(stage)
        tests.append(stats.periodic_test(resid_axis, phase, name, stage, period, "deg"))
    return tests


def _found(*tests: stats.StructureTest | None) -> list[stats.StructureTest]:
    """The tests that could be run (a test returns None when the data cannot support it)."""
    return [test for test in tests if test]


def largest_residuals(data: StageData, resid: NDArray[np.float64], n: int = 3) -> list[str]:
    """Where the largest disagreements sit on the grid, per axis (a sentence each)."""
    out = []
    for axis, name in enumerate(("x", "y")):
        idx = np.argsort(-np.abs(resid[:, axis]))[:n]
        where = ", ".join(f"({data.cmd_x_deg[i]:g}, {data.cmd_y_deg[i]:g})" for i in idx)
        out.append(
            f"largest {name} residuals ({', '.join(f'{resid[i, axis]:+.3g}' for i in idx)} deg) at "
            f"stage (θx, θy) = {where} deg"
        )
    return out
