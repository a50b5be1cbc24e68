"""Jobs on one angle per point: `scale` (the ADC sensor on the stage against the reference sensor,
seed 003) and `rotation` (the triaxial module on the rotary table, seed 002).

Each point is approached from below (backlash on one side), the instruments settle, readings are
averaged after the stated outlier rule and stored as they come, the fit is the method of
`tiltlab calibrate`, and points not used in the fit validate it.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.bench.readings import fresh_readings, robust_mean, settle
from service.bench.runtime import BenchRuntime
from service.calibration.model import CalibrationModel
from service.calibration.registry import Method, get_method
from service.calibration.uncertainty import COVERAGE
from service.errors import InputError
from service.instruments.base import Reading
from service.instruments.transport import DeviceError
from service.jobs.points import store_point
from service.jobs.procedure import (
    Columns,
    JobContext,
    Plan,
    PointProcedure,
    bench_epoch,
    validation_rng,
)
from service.jobs.requests import CalibrationRequest, RequestProblem
from service.storage.models import CalibrationJob, SettledPoint
from service.storage.samples import Sample

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
            t = bench.config.stage_bench().travel_deg
            return -t, t
        return -720.0, 720.0

    def plan(self, req: CalibrationRequest, bench: BenchRuntime) -> Plan[float]:
        if bench.kind != self.bench_kind:
            raise RequestProblem(
                "bench",
                f"{bench.name!r} is a {bench.kind} bench; {self.name} needs a "
                f"{self.bench_kind} bench",
            )
        for role in self.read_roles:
            if role not in bench.devices:
                raise RequestProblem("bench", f"{bench.name!r} has no {role}; {self.name} needs it")
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
        lo, hi = self.travel(bench)
        for i, a in enumerate(pts):
            if not lo <= a <= hi:
                raise RequestProblem(
                    "grid.angles_deg" if req.grid.angles_deg is not None else "grid.range_deg",
                    f"angle {i} ({a:g} deg) is outside [{lo:g}, {hi:g}] deg",
                )
        need = self.min_points
        if self.name == "scale" and req.method.startswith("poly") and req.method[4:].isdigit():
            need = int(req.method[4:]) + 2
        turntable = self.name == "turntable"
        # a turntable job reads each azimuth and its half-turn; a rotation is the same orientation
        # every full turn
        period = {"turntable": 180.0, "rotation": 360.0}.get(self.name)
        distinct = len({round(a % period, 6) % period for a in pts}) if period else len(set(pts))
        if distinct < need:
            modulo = f" (modulo {period:g} deg)" if period else ""
            raise RequestProblem(
                "grid", f"{distinct} distinct angles{modulo}; {req.method} needs at least {need}"
            )
        rng = validation_rng(len(pts), req.validation.n_points)
        val = [float(round(a, 4)) for a in rng.uniform(min(pts), max(pts), req.validation.n_points)]
        if turntable:
            if req.reference is None:
                raise RequestProblem(
                    "reference",
                    "a turntable job needs the axis reference: "
                    '{"north_arcsec": ..., "east_arcsec": ...}',
                )
            pts, val = (
                [x for a in pts for x in (a, a + 180.0)],
                [x for a in val for x in (a, a + 180.0)],
            )
        return Plan(pts, val, self.device_role, self.read_roles)

    def stored_point(self, value: Any) -> float:
        return float(value)

    async def measure(self, ctx: JobContext, index: int, point: float) -> None:
        await measure_angle(ctx, self, index, point)

    def columns(
        self, job: CalibrationJob, points: Sequence[SettledPoint], *, for_fit: bool
    ) -> Columns:
        by_device: dict[int, list[SettledPoint]] = {}
        for p in points:
            by_device.setdefault(p.device_id, []).append(p)
        request = job.parameters["request"]
        return columns(self, by_device, job.parameters["device_ids"], request.get("reference"))

    def validation(self, method: Method, model: CalibrationModel, cols: Columns) -> dict[str, Any]:
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


async def measure_angle(ctx: JobContext, proc: AngleProcedure, index: int, angle: float) -> None:
    bench, st = ctx.bench, ctx.request.settle
    began = bench.clock.monotonic()
    if proc.bench_kind == "stage":
        lo, _ = proc.travel(bench)
        await bench.move_stage(max(angle - APPROACH_SCALE_DEG, lo), 0.0)
        reached, _ = await bench.move_stage(angle, 0.0)
        settle_roles: tuple[str, ...] = ("reference_sensor",)
        tol = st.tolerance_deg
    else:
        await bench.move_rotary(angle - APPROACH_ROTARY_DEG)
        reached = await bench.move_rotary(angle)
        settle_roles = proc.read_roles
        tol = st.tolerance_deg
        if proc is ROTATION:
            tol = math.radians(tol)  # sines: a small angle in radians
    # when the controller was found standing (see measure_stage_point)
    stood = bench.stopped_bench_s
    t0 = await settle(
        bench, settle_roles, tolerance_deg=tol, window_s=st.window_s, timeout_s=st.timeout_s
    )
    n = ctx.request.samples_per_point
    timeout = max(5.0, 20 * n * max(bench.output_interval_s(r) for r in proc.read_roles))
    got = await asyncio.gather(
        *(fresh_readings(bench, r, n, after_bench_s=t0, timeout_s=timeout) for r in proc.read_roles)
    )
    ctx.bench_time.add(
        moving=stood - began,
        settling=t0 - stood,
        reading=max(r.bench_s for readings in got for r in readings) - t0,
    )
    for role, readings in zip(proc.read_roles, got):
        if role == "adc_sensor" and any(
            r.counts is not None and not 0 < r.counts < ADC_FULL_COUNTS for r in readings
        ):
            raise InputError(
                f"adc_sensor on {bench.port_of(role)} is at the end of its range (0 or "
                f"{ADC_FULL_COUNTS}"
                f" counts) at {angle:g} deg: the grid reaches beyond what the sensor measures"
            )
    to_epoch = bench_epoch(bench)
    rows: list[Sample] = []
    settled: dict[int, dict[str, Any]] = {}
    for role, readings in zip(proc.read_roles, got):
        dev = bench.device_ids[role]
        for r in readings:
            x, y, z = _channels(r)
            rows.append(
                Sample(
                    dev, to_epoch(r.bench_s), x, y, z, r.temp_c, ctx.job_id, index, "calibration"
                )
            )
        a = robust_mean(readings)
        m: list[float | None] = [*a.mean, *[None] * (3 - len(a.mean))]
        sd: list[float | None] = [*a.std, *[None] * (3 - len(a.std))]
        if len(a.mean) == 1:  # one channel (ADC counts): ch_y is stored as 0
            m[1], sd[1] = 0.0, None
        settled[dev] = {
            "point": index,
            "cmd_x_deg": reached,
            "cmd_y_deg": None,
            "n_samples": a.n_used,
            "t_start_s": to_epoch(a.t_start_s),
            "t_end_s": to_epoch(a.t_end_s),
            "ch_x_mean": m[0],
            "ch_y_mean": m[1],
            "ch_z_mean": m[2],
            "ch_x_std": sd[0],
            "ch_y_std": sd[1],
            "ch_z_std": sd[2],
            "temp_c_mean": a.temp_c,
        }
    await ctx.db(store_point, ctx.store, ctx.job_id, index, rows, settled)


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
        pts = {p.point: p for p in points_by_device.get(device_ids["turntable_sensor"], [])}
        pairs = [(pts[k], pts[k + 1]) for k in sorted(pts) if k % 2 == 0 and k + 1 in pts]
        axis = reference or {"north_arcsec": float("nan"), "east_arcsec": float("nan")}
        return {
            "cycle": np.zeros(len(pairs)),
            "azimuth_deg": np.array([a.cmd_x_deg for a, _ in pairs]),
            "n1_a": np.array([mrad(a.ch_x_mean) for a, _ in pairs]),
            "n2_a": np.array([mrad(a.ch_y_mean) for a, _ in pairs]),
            "n1_b": np.array([mrad(b.ch_x_mean) for _, b in pairs]),
            "n2_b": np.array([mrad(b.ch_y_mean) for _, b in pairs]),
            "ref_north_arcsec": np.full(len(pairs), axis["north_arcsec"]),
            "ref_east_arcsec": np.full(len(pairs), axis["east_arcsec"]),
        }
    if proc.name == "scale":
        ref = {p.point: p for p in points_by_device.get(device_ids["reference_sensor"], [])}
        adc = [p for p in points_by_device.get(device_ids["adc_sensor"], []) if p.point in ref]
        return {
            "point": np.array([p.point for p in adc], dtype=float),
            "ref_arcsec": np.array([ref[p.point].ch_x_mean * 3600.0 for p in adc]),
            "reading": np.array([p.ch_x_mean for p in adc]),
        }
    tri = points_by_device.get(device_ids["triaxial_sensor"], [])
    return {
        "point": np.array([p.point for p in tri], dtype=float),
        "theta_ref_deg": np.array([p.cmd_x_deg for p in tri]),
        "sx": np.array([p.ch_x_mean for p in tri]),
        "sy": np.array([p.ch_y_mean for p in tri]),
        "sz": np.array([p.ch_z_mean for p in tri]),
    }


def validation(
    proc: AngleProcedure, method: Method, model: CalibrationModel, cols: Columns
) -> dict[str, Any]:
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
                {"azimuth_deg": float(a), "error_deg": float(e)}
                for a, e in zip(cols["azimuth_deg"], err)
            ],
        }
    if proc.name == "scale":
        q, ref, meas = "angle_arcsec", cols["ref_arcsec"], out["angle_arcsec"]
        err = (meas - ref) / 3600.0
        against = "reference sensor x reading at each validation point"
        u = out.get("u_angle_arcsec")
    else:
        d = out["theta_deg"] - cols["theta_ref_deg"]
        err = (d + 180.0) % 360.0 - 180.0
        q, ref = "theta_deg", cols["theta_ref_deg"]
        meas = ref + err  # the measured angle on the reference's turn
        against = "rotary table angle at each validation point"
        u = out.get("u_theta_deg")
    points = []
    for i, p in enumerate(cols["point"]):
        # reference, corrected measurement and its expanded uncertainty: a certificate's validation
        # table
        point = {
            "point": int(p),
            "error_deg": float(abs(err[i])),
            f"reference_{q}": float(ref[i]),
            f"measured_{q}": float(meas[i]),
        }
        if u is not None:
            point[f"u_{q}"] = float(u[i])
        points.append(point)
    err = np.abs(err)
    return {
        "n_points": int(err.size),
        "rms_deg": float(np.sqrt(np.mean(err**2))),
        "max_deg": float(err.max()),
        "compared_with": against,
        "coverage_probability": COVERAGE,
        "points": points,
    }
