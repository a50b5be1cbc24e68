"""Jobs on one angle per point: `scale` (the ADC sensor on the stage against the reference sensor,
seed 003) and `rotation` (the triaxial module on the rotary table, seed 002).

Each point is approached from below (backlash on one side), the instruments settle, readings are
averaged after the stated outlier rule and stored as they come, the fit is the method of
`tiltlab calibrate`, and points not used in the fit validate it.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.bench.readings import fresh_readings, robust_mean, settle
from service.bench.runtime import BenchRuntime
from service.calibration.model import CalibrationModel
from service.calibration.registry import Method, get_method
from service.calibration.uncertainty import COVERAGE
from service.calibration.validation import validation_rng
from service.errors import InputError
from service.instruments.base import Reading
from service.instruments.transport import DeviceError
from service.jobs.points import store_point
from service.jobs.procedure import (
    Columns,
    JobContext,
    Plan,
    PointProcedure,
    RecordValidation,
    ValidationPoint,
    bench_epoch,
)
from service.jobs.requests import CalibrationRequest, Grid, RequestProblem
from service.storage.models import CalibrationJob, SettledPoint
from service.storage.samples import Sample
from service.storage.store.hashing import SettledPointFields

APPROACH_SCALE_DEG = 0.1
ADC_FULL_COUNTS = 4095  # the 12-bit converter of the adc_sensor role
APPROACH_ROTARY_DEG = 1.0


@dataclass(frozen=True)
class AngleProcedure(PointProcedure[float]):
    name: str
    kind: str  # calibration kind (record kind)
    bench_kind: str
    device_role: str  # the instrument calibrated (the record's device)
    read_roles: tuple[str, ...]  # settled and averaged at every point
    min_points: int

    def travel(self, bench: BenchRuntime) -> tuple[float, float]:
        if self.bench_kind == "stage":
            travel_deg = bench.config.stage_bench().travel_deg
            return -travel_deg, travel_deg
        return -720.0, 720.0

    def plan(self, req: CalibrationRequest, bench: BenchRuntime) -> Plan[float]:
        self._check_bench(bench)
        try:
            get_method(self.kind, req.method)
        except InputError as exc:
            raise RequestProblem("method", str(exc)) from None
        if req.grid is None or not req.grid.is_angles():
            raise RequestProblem(
                "grid",
                f"a {self.name} job needs angles: grid.angles_deg, or grid.range_deg and grid.n",
            )
        pts = req.grid.angles()
        self._check_travel(req.grid, pts, bench)
        self._check_distinct(req.method, pts)
        rng = validation_rng(len(pts), req.validation.n_points)
        val = [
            float(round(angle, 4))
            for angle in rng.uniform(min(pts), max(pts), req.validation.n_points)
        ]
        if self.name == "turntable":
            pts, val = _with_half_turns(req, pts, val)
        return Plan(pts, val, self.device_role, self.read_roles)

    def _check_bench(self, bench: BenchRuntime) -> None:
        """The bench is of the kind the procedure runs on and carries every instrument it reads."""
        if bench.kind != self.bench_kind:
            raise RequestProblem(
                "bench",
                f"{bench.name!r} is a {bench.kind} bench; {self.name} needs a "
                f"{self.bench_kind} bench",
            )
        for role in self.read_roles:
            if role not in bench.devices:
                raise RequestProblem("bench", f"{bench.name!r} has no {role}; {self.name} needs it")

    def _check_travel(self, grid: Grid, angles: list[float], bench: BenchRuntime) -> None:
        """Every angle within the bench's travel; RequestProblem names the first one outside."""
        lo, hi = self.travel(bench)
        for i, angle in enumerate(angles):
            if not lo <= angle <= hi:
                raise RequestProblem(
                    "grid.angles_deg" if grid.angles_deg is not None else "grid.range_deg",
                    f"angle {i} ({angle:g} deg) is outside [{lo:g}, {hi:g}] deg",
                )

    def _points_needed(self, method: str) -> int:
        """The fewest distinct angles the fit needs: the procedure's own minimum, or a scale
        polynomial's degree + 2."""
        if self.name == "scale" and method.startswith("poly") and method[4:].isdigit():
            return int(method[4:]) + 2
        return self.min_points

    def _check_distinct(self, method: str, angles: list[float]) -> None:
        """Enough distinct angles for the fit, counting the orientations that repeat (a turntable's
        half-turn, a rotation's full turn) once."""
        need = self._points_needed(method)
        # a turntable job reads each azimuth and its half-turn; a rotation is the same orientation
        # every full turn
        period = {"turntable": 180.0, "rotation": 360.0}.get(self.name)
        distinct = (
            len({round(angle % period, 6) % period for angle in angles})
            if period
            else len(set(angles))
        )
        if distinct < need:
            modulo = f" (modulo {period:g} deg)" if period else ""
            raise RequestProblem(
                "grid", f"{distinct} distinct angles{modulo}; {method} needs at least {need}"
            )

    def stored_point(self, value: Any) -> float:
        return float(value)

    async def measure(self, ctx: JobContext, index: int, point: float) -> None:
        await measure_angle(ctx, self, index, point)

    def columns(
        self, job: CalibrationJob, points: Sequence[SettledPoint], *, for_fit: bool
    ) -> Columns:
        by_device: dict[int, list[SettledPoint]] = {}
        for point in points:
            by_device.setdefault(point.device_id, []).append(point)
        request = job.parameters["request"]
        return columns(self, by_device, job.parameters["device_ids"], request.get("reference"))

    def validation(
        self, method: Method, model: CalibrationModel, cols: Columns
    ) -> RecordValidation:
        return validation(self, method, model, cols)


SCALE = AngleProcedure(
    "scale", "scale", "stage", "adc_sensor", ("reference_sensor", "adc_sensor"), 3
)
ROTATION = AngleProcedure(
    "rotation", "rotation", "rotary", "triaxial_sensor", ("triaxial_sensor",), 4
)
# turntable: each azimuth is read at a and a + 180 deg (points 2k and 2k + 1).
TURNTABLE = AngleProcedure(
    "turntable", "turntable", "rotary", "turntable_sensor", ("turntable_sensor",), 2
)


def _with_half_turns(
    req: CalibrationRequest, angles: list[float], validation_angles: list[float]
) -> tuple[list[float], list[float]]:
    """A turntable job's fit and validation angles, each followed by its half-turn (points 2k and
    2k + 1); such a job needs the axis reference."""
    if req.reference is None:
        raise RequestProblem(
            "reference",
            'a turntable job needs the axis reference: {"north_arcsec": ..., "east_arcsec": ...}',
        )
    return (
        [angle for azimuth in angles for angle in (azimuth, azimuth + 180.0)],
        [angle for azimuth in validation_angles for angle in (azimuth, azimuth + 180.0)],
    )


async def measure_angle(ctx: JobContext, proc: AngleProcedure, index: int, angle: float) -> None:
    bench, st = ctx.bench, ctx.request.settle
    began = bench.clock.monotonic()
    reached, settle_roles, tol = await _approach(bench, proc, angle, st.tolerance_deg)
    # when the controller was found standing (see measure_stage_point)
    stood = bench.stopped_bench_s
    t0 = await settle(
        bench,
        settle_roles,
        tolerance_deg=tol,
        window_s=st.window_s,
        timeout_s=st.timeout_s,
        since_bench_s=bench.stopped_after(began),
    )
    # a role read but not settled (the ADC beside the reference): readings are stamped when their
    # answer is parsed, so one asked during the move can arrive after t0 on a lagging line; only
    # those asked after its sync mark count
    unsettled = tuple(role for role in proc.read_roles if role not in settle_roles)
    after = max(t0, await bench.sync(unsettled)) if unsettled else t0
    n = ctx.request.samples_per_point
    timeout = max(5.0, 20 * n * max(bench.output_interval_s(role) for role in proc.read_roles))
    got = await asyncio.gather(
        *(
            fresh_readings(bench, role, n, after_bench_s=after, timeout_s=timeout)
            for role in proc.read_roles
        )
    )
    ctx.bench_time.add(
        moving=stood - began,
        settling=t0 - stood,
        reading=max(reading.bench_s for readings in got for reading in readings) - t0,
    )
    _check_adc_range(bench, proc.read_roles, got, angle)
    to_epoch = bench_epoch(bench)
    rows: list[Sample] = []
    settled: dict[int, SettledPointFields] = {}
    for role, readings in zip(proc.read_roles, got):
        dev = bench.device_ids[role]
        for reading in readings:
            x, y, z = _channels(reading)
            rows.append(
                Sample(
                    dev,
                    to_epoch(reading.bench_s),
                    x,
                    y,
                    z,
                    reading.temp_c,
                    ctx.job_id,
                    index,
                    "calibration",
                )
            )
        settled[dev] = _settled_means(readings, index, reached, to_epoch)
    await ctx.db(store_point, ctx.store, ctx.job_id, index, rows, settled)


async def _approach(
    bench: BenchRuntime, proc: AngleProcedure, angle: float, tolerance_deg: float
) -> tuple[float, tuple[str, ...], float]:
    """Move to `angle` from below (backlash taken up on one side): the angle reached, the roles that
    settle there and the tolerance they settle to."""
    if proc.bench_kind == "stage":
        lo, _ = proc.travel(bench)
        await bench.move_stage(max(angle - APPROACH_SCALE_DEG, lo), 0.0, passing=True)
        reached, _ = await bench.move_stage(angle, 0.0)
        return reached, ("reference_sensor",), tolerance_deg
    await bench.move_rotary(angle - APPROACH_ROTARY_DEG)
    reached = await bench.move_rotary(angle)
    if proc is ROTATION:
        # sines: a small angle in radians
        return reached, proc.read_roles, math.radians(tolerance_deg)
    return reached, proc.read_roles, tolerance_deg


def _check_adc_range(
    bench: BenchRuntime, roles: tuple[str, ...], got: Sequence[list[Reading]], angle: float
) -> None:
    """InputError when the ADC sensor read the end of its range: the grid reaches beyond what it
    measures."""
    for role, readings in zip(roles, got):
        if role == "adc_sensor" and any(
            reading.counts is not None and not 0 < reading.counts < ADC_FULL_COUNTS
            for reading in readings
        ):
            raise InputError(
                f"adc_sensor on {bench.port_of(role)} is at the end of its range (0 or "
                f"{ADC_FULL_COUNTS}"
                f" counts) at {angle:g} deg: the grid reaches beyond what the sensor measures"
            )


def _settled_means(
    readings: list[Reading], index: int, reached: float, to_epoch: Callable[[float], float]
) -> SettledPointFields:
    """One device's settled point: its readings averaged after the outlier rule, three channels
    (the missing ones None; one ADC channel stores ch_y as 0)."""
    averaged = robust_mean(readings)
    means: list[float | None] = [*averaged.mean, *[None] * (3 - len(averaged.mean))]
    stds: list[float | None] = [*averaged.std, *[None] * (3 - len(averaged.std))]
    if len(averaged.mean) == 1:  # one channel (ADC counts): ch_y is stored as 0
        means[1], stds[1] = 0.0, None
    return {
        "point": index,
        "cmd_x_deg": reached,
        "cmd_y_deg": None,
        "n_samples": averaged.n_used,
        "t_start_s": to_epoch(averaged.t_start_s),
        "t_end_s": to_epoch(averaged.t_end_s),
        "ch_x_mean": means[0],
        "ch_y_mean": means[1],
        "ch_z_mean": means[2],
        "ch_x_std": stds[0],
        "ch_y_std": stds[1],
        "ch_z_std": stds[2],
        "temp_c_mean": averaged.temp_c,
    }


def _channels(r: Reading) -> tuple[float, float, float | None]:
    if r.sx is not None:
        return r.sx, _value(r.sy), r.sz
    if r.counts is not None:
        return r.counts, 0.0, None
    return _value(r.x_deg), _value(r.y_deg), None


def _value(v: float | None) -> float:
    """A channel a reading of its kind always has."""
    if v is None:
        raise DeviceError("a reading came without one of its channels")
    return v


def mrad(deg: float) -> float:
    """The RS-485 inclinometer's reading as it sent it (milliradians; the driver hands out
    degrees)."""
    return math.radians(deg) * 1000.0


def columns(
    proc: AngleProcedure,
    points_by_device: dict[int, list[SettledPoint]],
    device_ids: dict[str, int],
    reference: dict[str, float] | None = None,
) -> Columns:
    """The dataset columns of a job's settled points, as `tiltlab calibrate` reads them."""
    if proc.name == "turntable":
        return _turntable_columns(
            points_by_device.get(device_ids["turntable_sensor"], []), reference
        )
    if proc.name == "scale":
        return _scale_columns(
            points_by_device.get(device_ids["reference_sensor"], []),
            points_by_device.get(device_ids["adc_sensor"], []),
        )
    return _rotation_columns(points_by_device.get(device_ids["triaxial_sensor"], []))


def _turntable_columns(points: list[SettledPoint], reference: dict[str, float] | None) -> Columns:
    """A turntable job's columns: each azimuth a whose half-turn was read too, the two readings in
    milliradians as the inclinometer sent them, and the stated axis reference."""
    pairs = _half_turn_pairs(points)
    axis = reference or {"north_arcsec": float("nan"), "east_arcsec": float("nan")}
    return {
        "cycle": np.zeros(len(pairs)),
        "azimuth_deg": np.array([at_a.cmd_x_deg for at_a, _ in pairs]),
        "n1_a": np.array([mrad(at_a.ch_x_mean) for at_a, _ in pairs]),
        "n2_a": np.array([mrad(at_a.ch_y_mean) for at_a, _ in pairs]),
        "n1_b": np.array([mrad(at_b.ch_x_mean) for _, at_b in pairs]),
        "n2_b": np.array([mrad(at_b.ch_y_mean) for _, at_b in pairs]),
        "ref_north_arcsec": np.full(len(pairs), axis["north_arcsec"]),
        "ref_east_arcsec": np.full(len(pairs), axis["east_arcsec"]),
    }


def _half_turn_pairs(points: list[SettledPoint]) -> list[tuple[SettledPoint, SettledPoint]]:
    """Each azimuth's point (2k) with its half-turn's (2k + 1), where both were read."""
    by_point = {point.point: point for point in points}
    return [
        (by_point[k], by_point[k + 1]) for k in sorted(by_point) if k % 2 == 0 and k + 1 in by_point
    ]


def _scale_columns(ref_points: list[SettledPoint], adc_points: list[SettledPoint]) -> Columns:
    """A scale job's columns: the ADC reading at each point the reference sensor read too, against
    the reference's x in arcseconds."""
    ref = {point.point: point for point in ref_points}
    adc = [point for point in adc_points if point.point in ref]
    return {
        "point": np.array([point.point for point in adc], dtype=float),
        "ref_arcsec": np.array([ref[point.point].ch_x_mean * 3600.0 for point in adc]),
        "reading": np.array([point.ch_x_mean for point in adc]),
    }


def _rotation_columns(tri: list[SettledPoint]) -> Columns:
    """A rotation job's columns: the triaxial module's three channels against the rotary table's
    angle."""
    return {
        "point": np.array([point.point for point in tri], dtype=float),
        "theta_ref_deg": np.array([point.cmd_x_deg for point in tri]),
        "sx": np.array([point.ch_x_mean for point in tri]),
        "sy": np.array([point.ch_y_mean for point in tri]),
        "sz": np.array([point.ch_z_mean for point in tri]),
    }


def validation(
    proc: AngleProcedure, method: Method, model: CalibrationModel, cols: Columns
) -> RecordValidation:
    key = "azimuth_deg" if proc.name == "turntable" else "point"
    if cols[key].size == 0:
        return {"n_points": 0, "rms_deg": None, "max_deg": None}
    out = method.correct(model, cols)
    if proc.name == "turntable":
        err = (
            np.hypot(
                out["north_arcsec"] - cols["ref_north_arcsec"],
                out["east_arcsec"] - cols["ref_east_arcsec"],
            )
            / 3600
        )
        return {
            "n_points": int(err.size),
            "rms_deg": float(np.sqrt(np.mean(err**2))),
            "max_deg": float(err.max()),
            "compared_with": "the stated axis reference (north, east) at each validation azimuth",
            "points": [
                {"azimuth_deg": float(azimuth), "error_deg": float(error)}
                for azimuth, error in zip(cols["azimuth_deg"], err)
            ],
        }
    if proc.name == "scale":
        quantity, ref, meas = "angle_arcsec", cols["ref_arcsec"], out["angle_arcsec"]
        err = (meas - ref) / 3600.0
        against = "reference sensor x reading at each validation point"
        u_meas = out.get("u_angle_arcsec")
    else:
        turned = out["theta_deg"] - cols["theta_ref_deg"]
        err = (turned + 180.0) % 360.0 - 180.0
        quantity, ref = "theta_deg", cols["theta_ref_deg"]
        meas = ref + err  # the measured angle on the reference's turn
        against = "rotary table angle at each validation point"
        u_meas = out.get("u_theta_deg")
    points: list[ValidationPoint] = []
    for i, point_number in enumerate(cols["point"]):
        # reference, corrected measurement and its expanded uncertainty: a certificate's validation
        # table
        points.append(
            _angle_point(
                quantity,
                int(point_number),
                float(abs(err[i])),
                (float(ref[i]), float(meas[i])),
                None if u_meas is None else float(u_meas[i]),
            )
        )
    err = np.abs(err)
    return {
        "n_points": int(err.size),
        "rms_deg": float(np.sqrt(np.mean(err**2))),
        "max_deg": float(err.max()),
        "compared_with": against,
        "coverage_probability": COVERAGE,
        "points": points,
    }


def _angle_point(
    quantity: str,
    point: int,
    error_deg: float,
    reference_measured: tuple[float, float],
    u_measured: float | None,
) -> ValidationPoint:
    """One validation point of a scale (`angle_arcsec`) or rotation (`theta_deg`) job: the
    reference, the corrected measurement and its expanded uncertainty where the model gives
    one."""
    reference, measured = reference_measured
    entry: ValidationPoint = {"point": point, "error_deg": error_deg}
    if quantity == "angle_arcsec":
        entry["reference_angle_arcsec"] = reference
        entry["measured_angle_arcsec"] = measured
        if u_measured is not None:
            entry["u_angle_arcsec"] = u_measured
    else:
        entry["reference_theta_deg"] = reference
        entry["measured_theta_deg"] = measured
        if u_measured is not None:
            entry["u_theta_deg"] = u_measured
    return entry
