"""Calibration records over HTTP: list, read, MODEL.json, the raw points as a dataset CSV, activate."""

from __future__ import annotations

import io
from typing import Annotated

import numpy as np
import sqlalchemy as sa
from fastapi import APIRouter, Query, Request
from fastapi.responses import Response

from service.api.auth import Operator, Reader
from service.api.deps import find_bench
from service.api.problems import ProblemError
from service.calibration.model import CalibrationModel
from service.calibration.registry import get_method
from service.calibration.residual_map import stage_residual_map
from service.columns import ROTATION_DATASET, SCALE_DATASET, STAGE_DATASET, TURNTABLE_DATASET
from service.datasets import format_value
from service.errors import InputError
from service.storage.errors import UnknownEntity
from service.storage.models import ActiveCalibration, CalibrationRecord

router = APIRouter(prefix="/records", tags=["records"])


def record_json(request: Request, r: CalibrationRecord, active: bool) -> dict:
    bench = request.app.state.jobs.bench_of_device(r.device_id)
    return {"id": r.id, "device_id": r.device_id, "bench": bench.name if bench else None, "kind": r.kind,
            "version": r.version, "method": r.method, "created_utc": r.created_at, "operator": r.operator,
            "job_id": r.job_id, "active": active, "validation": r.validation, "temp_c": r.temp_c,
            "conditions": (r.raw_data or {}).get("conditions"), "budget": (r.raw_data or {}).get("budget"),
            "raw_data": r.raw_data,
            "supersedes_id": r.supersedes_id, "content_sha256": r.content_sha256,
            "reference_standards": r.reference_standards,
            "status": request.app.state.store.record_status(r.id),  # draft | approved | rejected (LIMS approvals)
            "calibrated_range": calibrated_range(request, r)}


def calibrated_range(request: Request, r: CalibrationRecord) -> dict | None:
    """The table tilts a stage record was fitted on, per axis [min, max] in the reference sensor's frame."""
    try:
        seen = request.app.state.jobs.table_tilt_range_of(r)
    except InputError:  # a model this version cannot read states no range it can show
        return None
    if seen is None:
        return None
    return {"frame": "reference_sensor", "x_deg": seen["x"], "y_deg": seen["y"]}


def _record(request: Request, record_id: int) -> CalibrationRecord:
    try:
        return request.app.state.store.get_record(record_id)
    except UnknownEntity:
        raise ProblemError(404, "Unknown record", f"id: no calibration record {record_id}", field="id") from None


def _active_ids(request: Request) -> set[int]:
    with request.app.state.store.session() as s:
        return set(s.scalars(sa.select(ActiveCalibration.record_id)))


@router.get("")
def list_records(request: Request, _: Reader, device: Annotated[int | None, Query()] = None,
                 bench: str | None = None) -> dict:
    """Records newest first, of one device or of the devices of one bench."""
    stmt = sa.select(CalibrationRecord).order_by(CalibrationRecord.id.desc())
    if device is not None:
        stmt = stmt.where(CalibrationRecord.device_id == device)
    if bench is not None:
        stmt = stmt.where(CalibrationRecord.device_id.in_(list(find_bench(request, bench).device_ids.values())))
    with request.app.state.store.session() as s:
        rows = list(s.scalars(stmt))
    active = _active_ids(request)
    return {"records": [record_json(request, r, r.id in active) for r in rows]}


@router.get("/{record_id}")
def read(record_id: int, request: Request, _: Reader) -> dict:
    r = _record(request, record_id)
    return record_json(request, r, r.id in _active_ids(request))


@router.get("/{record_id}/model")
def model(record_id: int, request: Request, _: Reader) -> dict:
    """The record's MODEL.json, as `tiltlab correct --model` and `tiltlab level --model` take it."""
    return _record(request, record_id).model


@router.get("/{record_id}/points", response_class=Response,
            responses={200: {"content": {"text/csv": {}}, "description": "stage dataset CSV"}})
def points(record_id: int, request: Request, _: Reader) -> Response:
    """The settled points the record was fitted on as a dataset CSV of its kind: `tiltlab calibrate` on it gives the
    record's parameters exactly (stored values are written in their shortest exact decimal form)."""
    r = _record(request, record_id)
    if r.job_id is None:
        raise ProblemError(409, "No points", f"record {record_id} was not measured by a job of this daemon")
    cols = request.app.state.jobs.fit_columns(r.job_id, int((r.raw_data or {}).get("fit_points", 10**9)))
    buf = io.StringIO()
    order = {"stage": STAGE_DATASET, "scale": SCALE_DATASET, "rotation": ROTATION_DATASET,
             "turntable": TURNTABLE_DATASET}.get(r.kind, tuple(cols))
    names = [c for c in order if c in cols and np.isfinite(cols[c]).all()]
    buf.write(",".join(names) + "\r\n")
    for i in range(len(next(iter(cols.values())))):
        buf.write(",".join(format_value(c, cols[c][i], exact=True) for c in names) + "\r\n")
    return Response(buf.getvalue(), media_type="text/csv",
                    headers={"Content-Disposition": f'attachment; filename="record-{record_id}-points.csv"'})


@router.get("/{record_id}/residuals")
def residuals(record_id: int, request: Request, _: Reader) -> dict:
    """Per measured point of a stage record, the residual against the reference sensor before correction
    (measurement sensor raw) and after it (through the record's model, the computation of `tiltlab correct`);
    `role` says whether the point was fitted or kept for validation."""
    r = _record(request, record_id)
    if r.kind != "stage":
        raise ProblemError(409, "No residual map", f"record {record_id} is a {r.kind} record: residuals over a grid"
                           " are served for stage records")
    if r.job_id is None:
        raise ProblemError(409, "No points", f"record {record_id} was not measured by a job of this daemon")
    n_fit = int((r.raw_data or {}).get("fit_points", 10**9))
    cols = request.app.state.jobs.fit_columns(r.job_id, 10**9)
    model = CalibrationModel.from_json_dict(r.model, f"record {r.id}")
    return {"record_id": r.id, "method": r.method,
            **stage_residual_map(get_method("stage", r.method), model, cols, n_fit)}


@router.post("/{record_id}/activate")
def activate(record_id: int, request: Request, who: Operator) -> dict:
    """Make the record the active version of its device: /tilt and levelling use it from now on. A rejected
    record, or one whose stored content no longer matches its hash, is refused (409)."""
    r = _record(request, record_id)
    store = request.app.state.store
    why = store.unusable_reason(r.id)
    if why is not None:
        raise ProblemError(409, "Record not usable", f"{why}; it cannot be activated")
    current = store.active_record(r.device_id, r.kind)
    if current is None or current.id != r.id:
        store.activate(r.id, actor=who.name, reason="activated over HTTP", replaces=current.id if current else None)
    bench = request.app.state.jobs.bench_of_device(r.device_id)
    if bench is not None:
        request.app.state.jobs.load_active(bench)
    return record_json(request, store.get_record(r.id), True)
