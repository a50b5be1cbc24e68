"""The measurement a diagnosis plans: points the record's stored ones lack, measured as a job on the
bench.

A diagnosis with `measure: true` plans the shortest measurement that tests what the record's points
cannot (service.discrepancy.design) and runs it through the job manager like any job (it holds the
bench, shows its progress, can be cancelled or stopped, resumes after a restart). Each point is
approached from the side the plan says (from below or from above, per stage), settled and read as a
stage-grid point; nothing is fitted and no record is made: the diagnosis reads the points with the
record's.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from service.bench.runtime import BenchRuntime
from service.calibration.model import CalibrationModel
from service.calibration.registry import Method
from service.errors import InputError
from service.jobs.procedure import (
    Columns,
    JobContext,
    Outcome,
    Phase,
    Plan,
    PointProcedure,
    RecordValidation,
)
from service.jobs.requests import CalibrationRequest, RequestProblem
from service.jobs.stage_grid import SENSORS, measure_stage_point, stage_columns
from service.storage.models import CalibrationJob, SettledPoint

NAME = "diagnosis-measurement"

# stage x, stage y, approach x, approach y (+1 below, -1 above)
PlannedStagePoint = tuple[float, float, float, float]


class DiagnosisMeasurement(PointProcedure[PlannedStagePoint]):
    name = NAME
    kind = "stage"
    read_roles = SENSORS

    def plan(self, req: CalibrationRequest, bench: BenchRuntime) -> Plan[PlannedStagePoint]:
        raise RequestProblem(
            "procedure",
            "a diagnosis's measurement is planned and started by "
            "POST /records/{id}/diagnose with measure: true, not by POST /calibrations",
        )

    def stored_point(self, value: Any) -> PlannedStagePoint:
        x, y, dx, dy = value
        return float(x), float(y), float(dx), float(dy)

    async def measure(self, ctx: JobContext, index: int, point: PlannedStagePoint) -> None:
        x, y, dx, dy = point
        await measure_stage_point(ctx, index, x, y, dx, dy)

    def columns(
        self, job: CalibrationJob, points: Sequence[SettledPoint], *, for_fit: bool
    ) -> Columns:
        meas = [point for point in points if point.device_id == job.device_id]
        ref = [point for point in points if point.device_id != job.device_id]
        cols = stage_columns(ref, meas)
        planned = [self.stored_point(point) for point in job.parameters["fit_points"]]
        index = cols["point"].astype(int)
        cols["dir_x"] = np.array([planned[i][2] for i in index], dtype=float)
        cols["dir_y"] = np.array([planned[i][3] for i in index], dtype=float)
        if for_fit and not np.isfinite(cols["temp_c"]).all():
            del cols["temp_c"]
        return cols

    def validation(
        self, method: Method, model: CalibrationModel, cols: Columns
    ) -> RecordValidation:
        raise InputError(
            "a diagnosis's measurement validates nothing: it adds points to a record's"
        )

    async def run(self, ctx: JobContext) -> Outcome:
        job, bench = ctx.job, ctx.bench
        points = [self.stored_point(point) for point in job.parameters["fit_points"]]
        devices = self._devices_as_planned(job, bench)
        stored = await ctx.db(ctx.store.points.settled_points, job.id)
        done = set.intersection(
            *(
                {point.point for point in stored if point.device_id == device}
                for device in devices.values()
            )
        )
        await ctx.report(len(done), len(points), Phase.MEASURING)
        for i, point in enumerate(points):
            if i not in done:
                await self.measure(ctx, i, point)
                done.add(i)
                await ctx.report(len(done), len(points), Phase.MEASURING)
        return Outcome(job.device_id, self.kind, None, {}, {}, len(points))

    def _devices_as_planned(
        self, job: CalibrationJob, bench: BenchRuntime
    ) -> dict[str, int | None]:
        """The bench's instruments by role; InputError unless they are those the measurement was
        planned with (its points are measured with the same ones)."""
        devices = {read_role: bench.device_ids.get(read_role) for read_role in self.read_roles}
        if any(device is None for device in devices.values()) or devices != job.parameters.get(
            "device_ids", devices
        ):
            raise InputError(
                f"the bench's instruments are not those the measurement was planned with "
                f"({job.parameters.get('device_ids')}); its points cannot be measured with others"
            )
        return devices


DIAGNOSIS_MEASUREMENT = DiagnosisMeasurement()
