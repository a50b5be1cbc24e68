"""Diagnoses over HTTP: the model-discrepancy workflow on a stored record (start, read, report page,
list, adopt)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import HTMLResponse, JSONResponse, Response

from service.api.auth import Operator, Reader
from service.api.deps import DiagnosesDep, DiagnosesRepoDep, DiagnosisId, RecordId, RecordsRepoDep
from service.api.models.diagnoses import (
    AdoptRequest,
    DiagnoseRequest,
    Diagnoses,
    DiagnosisBody,
    DiagnosisPlan,
)
from service.api.models.paging import CURSOR, DEFAULT_PAGE, LIMIT, MAX_PAGE, json_answer
from service.api.models.problem import READ, WRITE, problem_responses
from service.api.models.records import Record
from service.api.offloop import in_thread, off_loop
from service.api.problems import ProblemError
from service.api.routers.records import RecordBodiesDep
from service.jobs.diagnosis import DiagnosisRunner
from service.jobs.requests import DB_ID_MAX
from service.storage.store import DiagnosesRepo

router = APIRouter(tags=["diagnoses"])


def _body(diagnoses: DiagnosesRepo, runner: DiagnosisRunner, diagnosis_id: int) -> DiagnosisBody:
    diagnosis, result = diagnoses.get_diagnosis(diagnosis_id)
    return DiagnosisBody.model_validate(runner.state_of(diagnosis, result))


@router.post(
    "/records/{record_id}/diagnose",
    status_code=202,
    response_model=DiagnosisBody,
    responses={
        200: {
            "model": DiagnosisPlan,
            "description": "plan_only: what the stored points show and "
            "the measurement measure: true would run",
        },
        **problem_responses(*WRITE, 404, 409),
    },
)
async def diagnose(
    record_id: RecordId,
    response: Response,
    records: RecordsRepoDep,
    diagnoses: DiagnosesRepoDep,
    runner: DiagnosesDep,
    who: Operator,
    body: DiagnoseRequest | None = None,
) -> DiagnosisBody | JSONResponse:
    """Run the model-discrepancy workflow (the one of `tiltlab discrepancy`) on the record's stored
    points, in the background and without the bench: 202 with the diagnosis and its Location. With
    `measure: true` it first measures, as a job on the record's bench (free, else 409), what the
    stored points cannot test, then diagnoses all the points; `plan_only: true` answers 200 with
    that plan, moving nothing."""
    body = body or DiagnoseRequest()
    record = await in_thread(records.get_record, record_id)
    if body.plan_only:
        plan = DiagnosisPlan.model_validate(await runner.plan(record, body.sensor, body.baseline))
        return JSONResponse(plan.model_dump(mode="json"), status_code=200)
    diagnosis = await runner.submit(
        record, body.sensor, body.baseline, who.name, measure=body.measure
    )
    response.headers["Location"] = f"/diagnoses/{diagnosis.id}"
    return await in_thread(_body, diagnoses, runner, diagnosis.id)


@router.get("/diagnoses", response_model=Diagnoses, responses=problem_responses(*READ))
@off_loop
def list_diagnoses(
    diagnoses: DiagnosesRepoDep,
    runner: DiagnosesDep,
    _: Reader,
    record: Annotated[int | None, Query(ge=1, le=DB_ID_MAX)] = None,
    cursor: Annotated[int | None, Query(ge=1, le=DB_ID_MAX, description=CURSOR)] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE, description=LIMIT)] = DEFAULT_PAGE,
) -> Response:
    """Diagnoses newest first, of one record or of all, a page at a time (`next_cursor` pages
    on)."""
    rows = diagnoses.list_diagnoses(record, before_id=cursor, limit=limit)
    return json_answer(
        Diagnoses(
            diagnoses=[
                DiagnosisBody.model_validate(runner.state_of(diagnosis, result))
                for diagnosis, result in rows
            ],
            next_cursor=rows[-1][0].id if len(rows) == limit else None,
        )
    )


@router.get(
    "/diagnoses/{diagnosis_id}",
    response_model=DiagnosisBody,
    responses=problem_responses(*READ, 404),
)
@off_loop
def read(
    diagnosis_id: DiagnosisId, diagnoses: DiagnosesRepoDep, runner: DiagnosesDep, _: Reader
) -> DiagnosisBody:
    return _body(diagnoses, runner, diagnosis_id)


@router.get(
    "/diagnoses/{diagnosis_id}/report",
    response_class=HTMLResponse,
    responses={
        200: {
            "content": {"text/html": {"schema": {"type": "string"}}},
            "description": "the workflow's report page",
        },
        **problem_responses(*READ, 404, 409),
    },
)
@off_loop
def report(diagnosis_id: DiagnosisId, diagnoses: DiagnosesRepoDep, _: Reader) -> HTMLResponse:
    """The workflow's HTML report (the page `tiltlab discrepancy --html` writes): figures inline."""
    _diagnosis, result = diagnoses.get_diagnosis(diagnosis_id)
    if result is None or result.report_html is None:
        state = "failed" if result is not None else "not finished"
        raise ProblemError(
            409, "No report", f"diagnosis {diagnosis_id} is {state}: it has no report"
        )
    return HTMLResponse(result.report_html)


@router.post(
    "/diagnoses/{diagnosis_id}/adopt",
    status_code=201,
    response_model=Record,
    responses=problem_responses(*WRITE, 404, 409),
)
async def adopt(
    diagnosis_id: DiagnosisId,
    response: Response,
    diagnoses: DiagnosesRepoDep,
    runner: DiagnosesDep,
    bodies: RecordBodiesDep,
    who: Operator,
    body: AdoptRequest | None = None,
) -> Record:
    """A new record version of the same device whose model includes the named effects the diagnosis
    found adoptable (those of `effects` only, when given), fitted on the points it diagnosed (with
    validation figures); a draft like any new record. 409 when it named nothing to add, or only
    effects these points cannot determine (the reason and the measurement that would, as the
    diagnosis said), or `effects` names one it did not find adoptable."""
    await in_thread(diagnoses.get_diagnosis, diagnosis_id)
    chosen = (
        None
        if body is None or body.effects is None
        else [str(fromkey) for fromkey in dict.fromkeys(body.effects)]
    )
    record = await runner.adopt(diagnosis_id, who.name, chosen)
    response.headers["Location"] = f"/records/{record.id}"
    return (await in_thread(bodies, [record]))[0]
