"""Diagnoses over HTTP: the model-discrepancy workflow on a stored record (start, read, report page, list, adopt)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse
from pydantic import BaseModel, ConfigDict

from service.api.auth import Operator, Reader
from service.api.problems import ProblemError
from service.storage.errors import UnknownEntity
from service.storage.models import CalibrationRecord, Diagnosis, DiagnosisResult

router = APIRouter(tags=["diagnoses"])


class DiagnoseRequest(BaseModel):
    """Which sensor's readings to explain, and the model the search starts from."""

    model_config = ConfigDict(extra="forbid")

    sensor: Literal["ref", "meas"] = "ref"
    baseline: Literal["kinematic", "linear"] = "kinematic"


def _record(request: Request, record_id: int) -> CalibrationRecord:
    try:
        return request.app.state.store.get_record(record_id)
    except UnknownEntity:
        raise ProblemError(404, "Unknown record", f"id: no calibration record {record_id}", field="id") from None


def _diagnosis(request: Request, diagnosis_id: int) -> tuple[Diagnosis, DiagnosisResult | None]:
    try:
        return request.app.state.store.get_diagnosis(diagnosis_id)
    except UnknownEntity:
        raise ProblemError(404, "Unknown diagnosis", f"id: no diagnosis {diagnosis_id}", field="id") from None


def _json(request: Request, diagnosis_id: int) -> dict:
    d, r = _diagnosis(request, diagnosis_id)
    return request.app.state.diagnoses.state_of(d, r)


@router.post("/records/{record_id}/diagnose", status_code=202)
async def diagnose(record_id: int, request: Request, response: Response, who: Operator,
                   body: DiagnoseRequest | None = None) -> dict:
    """Run the model-discrepancy workflow (the one of `tiltlab discrepancy`) on the record's stored points, in the
    background and without the bench: 202 with the diagnosis and its Location."""
    body = body or DiagnoseRequest()
    record = await run_in_threadpool(_record, request, record_id)
    d = await request.app.state.diagnoses.submit(record, body.sensor, body.baseline, who.name)
    response.headers["Location"] = f"/diagnoses/{d.id}"
    return await run_in_threadpool(_json, request, d.id)


@router.get("/diagnoses")
def list_diagnoses(request: Request, _: Reader, record: Annotated[int | None, Query(ge=1)] = None,
                   limit: Annotated[int, Query(ge=1, le=500)] = 100) -> dict:
    """Diagnoses newest first, of one record or of all."""
    runner = request.app.state.diagnoses
    rows = request.app.state.store.list_diagnoses(record, limit=limit)
    return {"diagnoses": [runner.state_of(d, r) for d, r in rows]}


@router.get("/diagnoses/{diagnosis_id}")
def read(diagnosis_id: int, request: Request, _: Reader) -> dict:
    return _json(request, diagnosis_id)


@router.get("/diagnoses/{diagnosis_id}/report", response_class=HTMLResponse,
            responses={200: {"content": {"text/html": {}}, "description": "the workflow's report page"}})
def report(diagnosis_id: int, request: Request, _: Reader) -> HTMLResponse:
    """The workflow's HTML report (the page `tiltlab discrepancy --html` writes): figures inline."""
    d, r = _diagnosis(request, diagnosis_id)
    if r is None or r.report_html is None:
        state = "failed" if r is not None else "not finished"
        raise ProblemError(409, "No report", f"diagnosis {diagnosis_id} is {state}: it has no report")
    return HTMLResponse(r.report_html)


@router.post("/diagnoses/{diagnosis_id}/adopt", status_code=201)
async def adopt(diagnosis_id: int, request: Request, response: Response, who: Operator) -> dict:
    """A new record version of the same device whose model includes the named effects, fitted on the same points
    (with validation figures); a draft like any new record. 409 when the diagnosis named nothing to add."""
    from service.api.routers.records import record_json

    await run_in_threadpool(_diagnosis, request, diagnosis_id)
    record = await request.app.state.diagnoses.adopt(diagnosis_id, who.name)
    response.headers["Location"] = f"/records/{record.id}"
    return await run_in_threadpool(record_json, request, record, False)
