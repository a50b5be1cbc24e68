"""Coverage of the averaged tilt's uncertainty (`GET /tilt?average_s`) over many calibrations.

An averaged tilt's U is mostly the record's parameter part, which every stand of one calibration
shares: the errors at the stands of one calibration are one draw of it, and their coverage is
nearly all or nothing (0.48-1.00 over one calibration's 60 stands on the rough bench). Coverage is a
statement over calibrations, and a figure within a few hundredths needs a few hundred of them. A
daemon's job takes seconds of real time each (its bench time sped up); here each calibration is made
in milliseconds by the daemon's own chain without the lines and the clock:

- the scenario's physics (`simulate_stage`, as the simulated world reads it): one positioning error
  per stand of the stage, shared by both sensors, each reading its own noise, quantised as the
  sensors' packed BCD sends it;
- the job's points: the job's grid in its order, each approached from below, `samples_per_point`
  readings of each sensor averaged as the job averages them (`robust_mean`), its columns
  (`stage_columns`), fit options, calibrated range and record budget (`budget_of_record`);
- the record as the daemon loads it (`active_model_of_points`: the model and budget through their
  JSON, the single-reading noise pooled from the points' spreads);
- the averaged tilt of a window of readings at rest at a random stand (`averaged_tilt`, what the
  route serves), against the stand's true table tilt.

`tests/daemon/test_tilt_coverage.py` checks that this chain gives, from a daemon job's stored
points, the record the daemon serves with (the same corrected tilt and uncertainty for the same
reading); the settling of the readings and the HTTP path are the daemon's own tests.
"""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.bench.corrected import averaged_tilt
from service.bench.readings import robust_mean
from service.calibration.budget import ReferenceStandard, UncertaintyBudget
from service.calibration.model import CalibrationModel, stored_table_tilt_range
from service.calibration.reading_noise import pooled_reading_noise
from service.calibration.registry import get_method
from service.instruments.base import Reading
from service.instruments.binary import decode_bcd, encode_angle, encode_temperature
from service.instruments.drivers.inclinometer import BinaryInclinometer
from service.instruments.sim import DEFAULT_OUTPUT_RATE_HZ
from service.jobs.active import ActiveModel
from service.jobs.budgets import budget_of_record
from service.jobs.requests import Grid
from service.jobs.stage_grid import StageGrid, stage_fit_columns, stage_fit_options
from service.physics.stage import StageBench, StageGeometry, simulate_stage
from service.reproduce.coverage import Row, Tally
from service.scenarios.model import StageScenario
from service.scenarios.run import effect_set, hardware_of, temperature
from service.storage.models import SettledPoint

# The daemon's coverage run (service/reproduce/daemon_coverage.py): a 5 x 5 grid at ±4°, 10
# readings a point, kinematic; stands inside ±3.5°.
GRID = Grid(x_deg=[-4.0, 4.0], y_deg=[-4.0, 4.0], n_x=5, n_y=5)
SAMPLES_PER_POINT = 10
POSES_WITHIN_DEG = 3.5
# the simulated sensors' output interval (their automatic output's rate)
OUTPUT_INTERVAL_S = 1.0 / DEFAULT_OUTPUT_RATE_HZ
# bench seconds from one point's readings to the next's (travel and settling): the time the
# environment's drifts see
POINT_SPACING_S = 4.0
# an averaged tilt's window: readings at rest, as many as a second or four of output
WINDOW_READINGS = (20, 100)
_EPOCH = dt.datetime(2026, 1, 1, tzinfo=dt.UTC)


def _wire_angle(deg: NDArray[np.float64]) -> NDArray[np.float64]:
    """Angles as the sensor's frame carries them (packed BCD, 4 decimals)."""
    return np.array([decode_bcd(encode_angle(float(v)), 4) for v in deg])


def _wire_temperature(temp_c: float) -> float:
    return decode_bcd(encode_temperature(temp_c), 2)


@dataclass
class VirtualStageBench:
    """A simulated stage scenario read without lines or clock: the stage stands at a commanded
    pose (to the pulse), a positioning error drawn once per stand, each sensor's readings at the
    output interval."""

    scenario: StageScenario
    rng: np.random.Generator
    t_s: float = 0.0
    pose_deg: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        self.bench: StageBench = hardware_of(self.scenario)
        self.effects = effect_set(self.scenario)
        self.geometry = StageGeometry.from_effects(self.bench, self.effects)
        self.stage_sigma_deg = self.effects.get("noise", "stage_sigma_deg")
        self.positioning_error_deg = (0.0, 0.0)
        self.direction = (1.0, 1.0)

    def stand_at(self, x_deg: float, y_deg: float, after_s: float) -> None:
        """Move to (x, y) (to the nearest pulse), `after_s` bench seconds later; a new stand."""
        pose = (
            round(x_deg / self.bench.pulse_x_deg) * self.bench.pulse_x_deg,
            round(y_deg / self.bench.pulse_y_deg) * self.bench.pulse_y_deg,
        )
        self.direction = (
            _direction(pose[0], self.pose_deg[0], self.direction[0]),
            _direction(pose[1], self.pose_deg[1], self.direction[1]),
        )
        self.pose_deg = pose
        self.t_s += after_s
        drawn = (
            self.rng.normal(0.0, self.stage_sigma_deg, 2)
            if self.stage_sigma_deg > 0
            else np.zeros(2)
        )
        self.positioning_error_deg = (float(drawn[0]), float(drawn[1]))

    def _simulate(self, n: int, noisy: bool) -> dict[str, NDArray[np.float64]]:
        times = self.t_s + OUTPUT_INTERVAL_S * np.arange(n)
        return simulate_stage(
            self.bench,
            self.effects,
            np.full(n, self.pose_deg[0]),
            np.full(n, self.pose_deg[1]),
            np.full(n, self.direction[0]),
            np.full(n, self.direction[1]),
            temperature(self.scenario.environment, times),
            times,
            rng=self.rng if noisy else None,
            geometry=self.geometry,
            positioning_error_deg=self.positioning_error_deg,
        )

    def read(self, n: int) -> dict[str, list[Reading]]:
        """`n` readings of each sensor at the present stand, as their drivers hand them on."""
        out = self._simulate(n, noisy=True)
        times = self.t_s + OUTPUT_INTERVAL_S * np.arange(n)
        temps = temperature(self.scenario.environment, times)
        self.t_s = float(times[-1]) + OUTPUT_INTERVAL_S
        readings: dict[str, list[Reading]] = {}
        for role, prefix in (("reference_sensor", "ref"), ("measurement_sensor", "meas")):
            x, y = _wire_angle(out[f"{prefix}_x_deg"]), _wire_angle(out[f"{prefix}_y_deg"])
            readings[role] = [
                Reading(
                    role,
                    float(t),
                    _EPOCH + dt.timedelta(seconds=float(t)),
                    x_deg=float(x[i]),
                    y_deg=float(y[i]),
                    temp_c=_wire_temperature(float(temps[i])),
                )
                for i, t in enumerate(times)
            ]
        return readings

    def true_tilt_deg(self) -> tuple[float, float]:
        """The table's true tilt at the present stand (its positioning error included)."""
        out = self._simulate(1, noisy=False)
        return float(out["tilt_x_deg"][0]), float(out["tilt_y_deg"][0])


def _direction(new_deg: float, old_deg: float, before: float) -> float:
    """The side a stage approached its new angle from (+1 from below): the last move's when it
    did not move."""
    if new_deg == old_deg:
        return before
    return 1.0 if new_deg > old_deg else -1.0


def _settled_point(
    index: int, command_deg: tuple[float, float], readings: list[Reading], device_id: int
) -> SettledPoint:
    """A point's settled means as the job stores them (`robust_mean` of its readings)."""
    averaged = robust_mean(readings)
    return SettledPoint(
        job_id=0,
        device_id=device_id,
        point=index,
        cmd_x_deg=command_deg[0],
        cmd_y_deg=command_deg[1],
        n_samples=averaged.n_used,
        t_start_s=averaged.t_start_s,
        t_end_s=averaged.t_end_s,
        ch_x_mean=averaged.mean[0],
        ch_y_mean=averaged.mean[1],
        ch_x_std=averaged.std[0],
        ch_y_std=averaged.std[1],
        temp_c_mean=averaged.temp_c,
    )


def active_model_of_points(
    method_name: str,
    bench: StageBench,
    reference_points: Sequence[SettledPoint],
    measurement_points: Sequence[SettledPoint],
    resolutions_deg: dict[str, float | None],
    standards: Sequence[ReferenceStandard] = (),
) -> ActiveModel:
    """The record a fixed stage-grid job makes of its settled points, as the daemon loads it to
    correct with: the job's columns, fit options and calibrated range, the record's budget, the
    model and budget through their stored JSON, the single-reading noise pooled from the
    measurement sensor's points."""
    method = get_method("stage", method_name)
    cols = stage_fit_columns(reference_points, measurement_points)
    model = method.fit(cols, stage_fit_options(bench, "scenario"))
    StageGrid().fitted(model, cols)
    budget = budget_of_record(method, model, cols, standards, resolutions_deg)
    stored_model = CalibrationModel.from_json_dict(
        json.loads(json.dumps(model.to_json_dict())), "virtual record"
    )
    stored_budget: UncertaintyBudget = json.loads(json.dumps(budget))
    return ActiveModel(
        0,
        1,
        method_name,
        stored_model,
        method,
        stored_budget,
        table_tilt_range_deg=stored_table_tilt_range(stored_model),
        reading_noise=pooled_reading_noise(
            (point.n_samples, point.ch_x_std, point.ch_y_std) for point in measurement_points
        ),
    )


def calibrate(virtual: VirtualStageBench, method_name: str = "kinematic") -> ActiveModel:
    """One calibration of GRID (SAMPLES_PER_POINT readings a point) on the virtual bench."""
    reference: list[SettledPoint] = []
    measurement: list[SettledPoint] = []
    for index, (x_deg, y_deg) in enumerate(GRID.stage_points()):
        # approached from below, as the job does
        virtual.stand_at(x_deg - 0.1, y_deg - 0.1, 0.0)
        virtual.stand_at(x_deg, y_deg, POINT_SPACING_S)
        got = virtual.read(SAMPLES_PER_POINT)
        reference.append(_settled_point(index, (x_deg, y_deg), got["reference_sensor"], 1))
        measurement.append(_settled_point(index, (x_deg, y_deg), got["measurement_sensor"], 2))
    # in the order the bench lists its sensors, as the job's record states them
    resolutions: dict[str, float | None] = {
        "reference_sensor": BinaryInclinometer.resolution_deg,
        "measurement_sensor": BinaryInclinometer.resolution_deg,
    }
    return active_model_of_points(method_name, virtual.bench, reference, measurement, resolutions)


@dataclass
class AveragedErrors:
    """Per averaged tilt (rows) and axis (columns x, y): the error (corrected mean - true tilt) and
    the stated expanded uncertainty; the readings each mean is of."""

    errors: NDArray[np.float64]
    expanded: NDArray[np.float64]
    readings: NDArray[np.float64]


def averaged_errors(
    scenario: StageScenario, calibrations: int, stands: int, seed: int
) -> AveragedErrors:
    """`calibrations` calibrations of the scenario's bench (fresh noise each), then at each of
    `stands` random stands inside the calibrated range an averaged tilt of a window of readings at
    rest, against the stand's true tilt."""
    rng = np.random.default_rng(seed)
    errors, expanded, counts = [], [], []
    for _ in range(calibrations):
        virtual = VirtualStageBench(scenario, np.random.default_rng(rng.integers(2**63)))
        active = calibrate(virtual)
        for _ in range(stands):
            x_deg, y_deg = rng.uniform(-POSES_WITHIN_DEG, POSES_WITHIN_DEG, 2).round(3)
            virtual.stand_at(float(x_deg), float(y_deg), POINT_SPACING_S)
            n = int(rng.integers(WINDOW_READINGS[0], WINDOW_READINGS[1] + 1))
            window = virtual.read(n)["measurement_sensor"]
            table = averaged_tilt(active, window, window[-1].bench_s - window[0].bench_s)
            truth = virtual.true_tilt_deg()
            errors.append([_value(table["x_deg"]) - truth[0], _value(table["y_deg"]) - truth[1]])
            expanded.append(
                [
                    _value(table["expanded_uncertainty_x_deg"]),
                    _value(table["expanded_uncertainty_y_deg"]),
                ]
            )
            counts.append(n)
    return AveragedErrors(np.asarray(errors), np.asarray(expanded), np.asarray(counts, dtype=float))


def _value(value: Any) -> float:
    if value is None:
        raise RuntimeError("the averaged tilt states no value or uncertainty")
    return float(value)


def averaged_rows(
    scenarios: Sequence[tuple[str, StageScenario]], calibrations: int, stands: int, seed: int = 0
) -> list[Row]:
    """Coverage rows (per scenario and axis) of the averaged tilt over `calibrations` virtual
    calibrations of `stands` stands each."""
    rows: list[Row] = []
    for name, scenario in scenarios:
        got = averaged_errors(scenario, calibrations, stands, seed)
        tally = Tally()
        for i, axis in enumerate("xy"):
            tally.add(axis, got.errors[:, i], got.expanded[:, i])
        rows += tally.rows(
            "averaged",
            "averaged tilt (daemon's chain)",
            f"{name}, {calibrations} calibrations x {stands} stands",
        )
    return rows
