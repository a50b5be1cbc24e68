"""Calibration records over HTTP: list, read, MODEL.json, the raw points as a dataset CSV,
activate."""

from __future__ import annotations

import io
from collections.abc import Sequence
from typing import Annotated, TypedDict

import numpy as np
from fastapi import APIRouter, Depends, Query
from fastapi.responses import Response

from service.api.auth import Operator, Reader
from service.api.deps import (
    ApprovalsRepoDep,
    BenchesDep,
    DevicesRepoDep,
    JobsDep,
    RecordId,
    RecordsRepoDep,
    StoreDep,
    find_bench,
)
from service.api.models.paging import CURSOR, DEFAULT_PAGE, LIMIT, MAX_PAGE, json_answer
from service.api.models.problem import READ, WRITE, problem_responses
from service.api.models.records import ModelFile, Record, RecordList, Residuals
from service.api.offloop import off_loop
from service.api.problems import ProblemError
from service.calibration.model import CalibrationModel, stored_range
from service.calibration.registry import get_method
from service.calibration.residual_map import stage_residual_map
from service.errors import InputError
from service.io.columns import ROTATION_DATASET, SCALE_DATASET, STAGE_DATASET, TURNTABLE_DATASET
from service.io.datasets import format_value
from service.jobs.budgets import with_traceability
from service.jobs.manager import JobManager
from service.jobs.requests import DB_ID_MAX
from service.lims.certificates import record_conformity
from service.storage.models import CalibrationRecord
from service.storage.store import ApprovalsRepo, DevicesRepo, RecordsRepo, Store

router = APIRouter(prefix="/records", tags=["records"])


class CsvResponse(Response):
    media_type = "text/csv"


class RecordBodies:
    """Records as the routes show them: with their bench, whether active and their approval
    status."""

    def __init__(
        self,
        records: RecordsRepoDep,
        approvals: ApprovalsRepoDep,
        devices: DevicesRepoDep,
        jobs: JobsDep,
        store: StoreDep,
    ) -> None:
        self.records, self.approvals, self.devices, self.jobs, self.store = (
            records,
            approvals,
            devices,
            jobs,
            store,
        )

    def __call__(self, rows: Sequence[CalibrationRecord]) -> list[Record]:
        """The bodies of these records, read in four queries however many they are (and, for the
        records of an order with a specification, those their statements of conformity need)."""
        return record_bodies(
            self.records, self.approvals, self.devices, self.jobs, rows, self.store
        )

    def page(self, rows: Sequence[CalibrationRecord]) -> list[Record]:
        """The bodies of a page of records read without their models (see `page_ranges`)."""
        return record_bodies(
            self.records,
            self.approvals,
            self.devices,
            self.jobs,
            rows,
            self.store,
            page_ranges(self.records, self.jobs, rows),
        )


RecordBodiesDep = Annotated[RecordBodies, Depends()]


class RangeBody(TypedDict):
    """A stage record's calibrated range as its body states it: per axis [min, max] of the table
    tilts it was fitted on, in the reference sensor's frame."""

    frame: str
    x_deg: list[float]
    y_deg: list[float]


def record_bodies(
    records: RecordsRepo,
    approvals: ApprovalsRepo,
    devices: DevicesRepo,
    jobs: JobManager,
    rows: Sequence[CalibrationRecord],
    store: Store,
    ranges: dict[int, RangeBody | None] | None = None,
) -> list[Record]:
    """Records with their bench, whether active, their approval status, their budget saying whether
    it is traceable and, where their order has a specification, their statements of conformity (and
    their calibrated ranges, from `ranges` where given)."""
    active = records.active_record_ids()
    specified = store.orders.specified_jobs([row.job_id for row in rows if row.job_id is not None])
    status = approvals.record_statuses([row.id for row in rows])
    # in a fleet a record's device may hang off another daemon's bench: the database knows its name
    elsewhere = devices.bench_names_of_devices(
        {row.device_id for row in rows if jobs.bench_of_device(row.device_id) is None}
    )
    out = []
    for row in rows:
        bench = jobs.bench_of_device(row.device_id)
        bench_name = bench.name if bench else elsewhere.get(row.device_id)
        out.append(
            _record_body(
                row,
                bench_name,
                store=store,
                jobs=jobs,
                active=active,
                specified=specified,
                status=status,
                ranges=ranges,
            )
        )
    return out


def _record_body(
    row: CalibrationRecord,
    bench_name: str | None,
    *,
    store: Store,
    jobs: JobManager,
    active: set[int],
    specified: set[int],
    status: dict[int, str],
    ranges: dict[int, RangeBody | None] | None,
) -> Record:
    """One record's body: its row, with what record_bodies looked up for the whole page."""
    raw = row.raw_data or {}
    return Record.model_validate(
        {
            "id": row.id,
            "device_id": row.device_id,
            "bench": bench_name,
            "kind": row.kind,
            "version": row.version,
            "method": row.method,
            "created_utc": row.created_at,
            "operator": row.operator,
            "job_id": row.job_id,
            "active": row.id in active,
            "validation": row.validation,
            "temp_c": row.temp_c,
            "conditions": raw.get("conditions"),
            "budget": with_traceability(raw.get("budget")),
            "conformity": record_conformity(store, row) if row.job_id in specified else None,
            "raw_data": row.raw_data,
            "supersedes_id": row.supersedes_id,
            "content_sha256": row.content_sha256,
            "reference_standards": row.reference_standards,
            "status": status[row.id],  # draft | approved | rejected (LIMS approvals)
            "calibrated_range": ranges[row.id]
            if ranges is not None
            else calibrated_range(jobs, row),
            "bench_seconds": raw.get("bench_seconds"),
        }
    )


def calibrated_range(jobs: JobManager, r: CalibrationRecord) -> RangeBody | None:
    """The table tilts a stage record was fitted on, per axis [min, max] in the reference sensor's
    frame."""
    try:
        seen = jobs.table_tilt_range_of(r)
    except InputError:  # a model this version cannot read states no range it can show
        return None
    return _range_body(seen)


def _range_body(seen: dict[str, list[float]] | None) -> RangeBody | None:
    return (
        None
        if seen is None
        else {"frame": "reference_sensor", "x_deg": seen["x"], "y_deg": seen["y"]}
    )


def page_ranges(
    records: RecordsRepo, jobs: JobManager, rows: Sequence[CalibrationRecord]
) -> dict[int, RangeBody | None]:
    """The calibrated ranges of a page of records read without their models: known ones from memory,
    the rest from what each model states (extracted by the database), and a record whose model
    states none (made before models kept it) read whole, once."""
    out: dict[int, RangeBody | None] = {}
    missing = []
    for row in rows:
        known, seen = jobs.known_range(row.id)
        if known:
            out[row.id] = _range_body(seen)
        elif row.kind != "stage":
            jobs.remember_range(row.id, None)
            out[row.id] = None
        else:
            missing.append(row.id)
    for record_id, stated in records.fitted_ranges(missing).items():
        seen = stored_range(stated)
        if seen is None:  # an older model: worked out from the record's own points, once
            out[record_id] = calibrated_range(jobs, records.get_record(record_id))
            continue
        jobs.remember_range(record_id, seen)
        out[record_id] = _range_body(seen)
    return out


@router.get("", response_model=RecordList, responses=problem_responses(*READ, 404))
@off_loop
def list_records(
    benches: BenchesDep,
    records: RecordsRepoDep,
    devices: DevicesRepoDep,
    bodies: RecordBodiesDep,
    _: Reader,
    device: Annotated[int | None, Query(ge=1, le=DB_ID_MAX, description="a device's id")] = None,
    bench: Annotated[str | None, Query(max_length=100)] = None,
    cursor: Annotated[int | None, Query(ge=1, le=DB_ID_MAX, description=CURSOR)] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE, description=LIMIT)] = DEFAULT_PAGE,
) -> Response:
    """Records newest first, of one device or of the devices of one bench, a page at a time:
    `next_cursor` (null on the last page) pages on."""
    of_bench: list[int] | None = None
    if bench is not None:
        device_ids = (
            list(benches[bench].device_ids.values())
            if bench in benches
            else devices.device_ids_of_bench(bench)
        )  # another daemon's bench of the lab
        if device_ids is None:
            find_bench(benches, bench)  # the 404 naming the benches there are
        of_bench = device_ids or []
    found = records.newest_first(
        device_id=device, device_ids=of_bench, before_id=cursor, limit=limit, with_model=False
    )
    return json_answer(
        RecordList(
            records=bodies.page(found), next_cursor=found[-1].id if len(found) == limit else None
        )
    )


@router.get("/{record_id}", response_model=Record, responses=problem_responses(*READ, 404))
@off_loop
def read(
    record_id: RecordId, records: RecordsRepoDep, bodies: RecordBodiesDep, _: Reader
) -> Record:
    return bodies([records.get_record(record_id)])[0]


@router.get(
    "/{record_id}/model",
    response_model=ModelFile,
    response_model_exclude_unset=True,
    responses=problem_responses(*READ, 404),
)
@off_loop
def model(record_id: RecordId, records: RecordsRepoDep, _: Reader) -> ModelFile:
    """The record's MODEL.json, as `tiltlab correct --model` and `tiltlab level --model` take it."""
    return ModelFile.model_validate(records.get_record(record_id).model)


@router.get(
    "/{record_id}/points",
    response_class=CsvResponse,
    responses={
        200: {
            "content": {"text/csv": {"schema": {"type": "string"}}},
            "description": "the record's fit points as a dataset CSV of its kind",
        },
        **problem_responses(*READ, 404, 409),
    },
)
@off_loop
def points(record_id: RecordId, jobs: JobsDep, records: RecordsRepoDep, _: Reader) -> Response:
    """The settled points the record was fitted on as a dataset CSV of its kind: `tiltlab calibrate`
    on it gives the record's parameters exactly (stored values are written in their shortest exact
    decimal form)."""
    record = records.get_record(record_id)
    if record.job_id is None:
        raise ProblemError(
            409, "No points", f"record {record_id} was not measured by a job of this daemon"
        )
    cols = jobs.fit_columns(record.job_id, int((record.raw_data or {}).get("fit_points", 10**9)))
    buf = io.StringIO()
    order = {
        "stage": STAGE_DATASET,
        "scale": SCALE_DATASET,
        "rotation": ROTATION_DATASET,
        "turntable": TURNTABLE_DATASET,
    }.get(record.kind, tuple(cols))
    names = [column for column in order if column in cols and np.isfinite(cols[column]).all()]
    buf.write(",".join(names) + "\r\n")
    for i in range(len(next(iter(cols.values())))):
        buf.write(
            ",".join(format_value(column, cols[column][i], exact=True) for column in names) + "\r\n"
        )
    return CsvResponse(
        buf.getvalue(),
        headers={"Content-Disposition": f'attachment; filename="record-{record_id}-points.csv"'},
    )


@router.get(
    "/{record_id}/residuals", response_model=Residuals, responses=problem_responses(*READ, 404, 409)
)
@off_loop
def residuals(record_id: RecordId, jobs: JobsDep, records: RecordsRepoDep, _: Reader) -> Residuals:
    """Per measured point of a stage record, the residual against the reference sensor before
    correction (measurement sensor raw) and after it (through the record's model, the computation of
    `tiltlab correct`); `role` says whether the point was fitted or kept for validation."""
    record = records.get_record(record_id)
    if record.kind != "stage":
        raise ProblemError(
            409,
            "No residual map",
            f"record {record_id} is a {record.kind} record: residuals over a grid"
            " are served for stage records",
        )
    if record.job_id is None:
        raise ProblemError(
            409, "No points", f"record {record_id} was not measured by a job of this daemon"
        )
    n_fit = int((record.raw_data or {}).get("fit_points", 10**9))
    cols = jobs.fit_columns(record.job_id, 10**9)
    fitted = CalibrationModel.from_json_dict(record.model, f"record {record.id}")
    return Residuals.model_validate(
        {
            "record_id": record.id,
            "method": record.method,
            **stage_residual_map(get_method("stage", record.method), fitted, cols, n_fit),
        }
    )


@router.post(
    "/{record_id}/activate", response_model=Record, responses=problem_responses(*WRITE, 404, 409)
)
@off_loop
def activate(
    record_id: RecordId,
    jobs: JobsDep,
    records: RecordsRepoDep,
    bodies: RecordBodiesDep,
    who: Operator,
) -> Record:
    """Make the record the active version of its device: /tilt and levelling use it from now on. A
    rejected record, or one whose stored content no longer matches its hash, is refused (409)."""
    record = records.get_record(record_id)
    why = records.unusable_reason(record.id)
    if why is not None:
        raise ProblemError(409, "Record not usable", f"{why}; it cannot be activated")
    current = records.active_record(record.device_id, record.kind)
    if current is None or current.id != record.id:
        records.activate(
            record.id,
            actor=who.name,
            reason="activated over HTTP",
            replaces=current.id if current else None,
        )
    bench = jobs.bench_of_device(record.device_id)
    if bench is not None:
        jobs.load_active(bench)
    return bodies([records.get_record(record.id)])[0]
