"""Diagnoses over HTTP: the model-discrepancy workflow on a stored record (start, read, report page, list, adopt)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse

from service.api.auth import Operator, Reader
from service.api.deps import DiagnosesDep, DiagnosesRepoDep, DiagnosisId, RecordId, RecordsRepoDep
from service.api.models.diagnoses import DiagnoseRequest, Diagnoses, DiagnosisBody
from service.api.models.problem import READ, WRITE, problem_responses
from service.api.models.records import Record
from service.api.problems import ProblemError
from service.api.routers.records import RecordBodiesDep
from service.jobs.diagnosis import DiagnosisRunner
from service.jobs.requests import DB_ID_MAX
from service.storage.store import DiagnosesRepo

router = APIRouter(tags=["diagnoses"])


def _body(diagnoses: DiagnosesRepo, runner: DiagnosisRunner, diagnosis_id: int) -> DiagnosisBody:
    d, r = diagnoses.get_diagnosis(diagnosis_id)
    return DiagnosisBody.model_validate(runner.state_of(d, r))


@router.post("/records/{record_id}/diagnose", status_code=202, response_model=DiagnosisBody,
             responses=problem_responses(*WRITE, 404, 409))
async def diagnose(record_id: RecordId, response: Response, records: RecordsRepoDep, diagnoses: DiagnosesRepoDep,
                   runner: DiagnosesDep, who: Operator,
                   body: DiagnoseRequest | None = None) -> DiagnosisBody:
    """Run the model-discrepancy workflow (the one of `tiltlab discrepancy`) on the record's stored points, in the
    background and without the bench: 202 with the diagnosis and its Location."""
    body = body or DiagnoseRequest()
    record = await run_in_threadpool(records.get_record, record_id)
    d = await runner.submit(record, body.sensor, body.baseline, who.name)
    response.headers["Location"] = f"/diagnoses/{d.id}"
    return await run_in_threadpool(_body, diagnoses, runner, d.id)


@router.get("/diagnoses", response_model=Diagnoses, responses=problem_responses(*READ))
def list_diagnoses(diagnoses: DiagnosesRepoDep, runner: DiagnosesDep, _: Reader,
                   record: Annotated[int | None, Query(ge=1, le=DB_ID_MAX)] = None,
                   limit: Annotated[int, Query(ge=1, le=500)] = 100) -> Diagnoses:
    """Diagnoses newest first, of one record or of all."""
    rows = diagnoses.list_diagnoses(record, limit=limit)
    return Diagnoses(diagnoses=[DiagnosisBody.model_validate(runner.state_of(d, r)) for d, r in rows])


@router.get("/diagnoses/{diagnosis_id}", response_model=DiagnosisBody, responses=problem_responses(*READ, 404))
def read(diagnosis_id: DiagnosisId, diagnoses: DiagnosesRepoDep, runner: DiagnosesDep, _: Reader) -> DiagnosisBody:
    return _body(diagnoses, runner, diagnosis_id)


@router.get("/diagnoses/{diagnosis_id}/report", response_class=HTMLResponse, responses={
    200: {"content": {"text/html": {"schema": {"type": "string"}}}, "description": "the workflow's report page"},
    **problem_responses(*READ, 404, 409)})
def report(diagnosis_id: DiagnosisId, diagnoses: DiagnosesRepoDep, _: Reader) -> HTMLResponse:
    """The workflow's HTML report (the page `tiltlab discrepancy --html` writes): figures inline."""
    _d, r = diagnoses.get_diagnosis(diagnosis_id)
    if r is None or r.report_html is None:
        state = "failed" if r is not None else "not finished"
        raise ProblemError(409, "No report", f"diagnosis {diagnosis_id} is {state}: it has no report")
    return HTMLResponse(r.report_html)


@router.post("/diagnoses/{diagnosis_id}/adopt", status_code=201, response_model=Record,
             responses=problem_responses(401, 403, 404, 409, 422))
async def adopt(diagnosis_id: DiagnosisId, response: Response, diagnoses: DiagnosesRepoDep, runner: DiagnosesDep,
                bodies: RecordBodiesDep, who: Operator) -> Record:
    """A new record version of the same device whose model includes the named effects, fitted on the same points
    (with validation figures); a draft like any new record. 409 when the diagnosis named nothing to add."""
    await run_in_threadpool(diagnoses.get_diagnosis, diagnosis_id)
    record = await runner.adopt(diagnosis_id, who.name)
    response.headers["Location"] = f"/records/{record.id}"
    return (await run_in_threadpool(bodies, [record]))[0]
