"""LIMS integration over HTTP: reference standards, approvals, certificates, orders, the event feed, webhooks."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Header, Query, Request
from fastapi.responses import HTMLResponse, JSONResponse, Response
from pydantic import BaseModel, ConfigDict, Field

from service.api.auth import Admin, Operator, Reader
from service.api.problems import ProblemError
from service.lims import dcc
from service.lims.certificates import IntegrityFailure, NotApproved, NotConfigured, issue_certificate
from service.storage.errors import ConflictError, UnknownEntity
from service.storage.feed import EVENT_TYPES, decode_cursor, encode_cursor, event_json
from service.storage.lims import SelfApproval
from service.storage.models import Order, RecordApproval, ReferenceStandard

router = APIRouter(tags=["lims"])

_XML: dict[int | str, dict[str, Any]] = {200: {"content": {"application/xml": {}}, "description": "the DCC 3.3.0 certificate"}}


def _store(request: Request):  # type: ignore[no-untyped-def]
    return request.app.state.store


def _not_found(exc: UnknownEntity, field: str = "id") -> ProblemError:
    return ProblemError(404, "Not found", str(exc), field=field)


# ---------------------------------------------------------------- reference standards


class StandardIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(max_length=100, examples=["reference inclinometer"])
    serial: str = Field(max_length=100)
    model: str | None = Field(None, max_length=100)
    certificate_number: str = Field(max_length=100)
    certificate_sha256: str = Field(description="SHA-256 of the standard's calibration certificate file (64 hex digits)")
    calibrated_on: dt.date
    due_on: dt.date
    expanded_uncertainty_deg: float | None = Field(
        None, gt=0, allow_inf_nan=False, examples=[0.001],
        description="expanded uncertainty U of the standard's angle, in degrees, as its certificate states it; "
                    "u = U / coverage_factor enters every result calibrated against it. Read from `uncertainty` "
                    "when not given; a standard with neither cannot be named by a job (422)")
    coverage_factor: float = Field(2.0, ge=1, allow_inf_nan=False, description="the coverage factor k of U")
    uncertainty: str = Field("", max_length=500, examples=["0.001 deg (k = 2)"],
                             description="the certificate's wording of the uncertainty (a remark)")


def standard_json(s: ReferenceStandard, today: dt.date, due_soon_days: int) -> dict[str, Any]:
    days = (s.due_on - today).days
    return {"id": s.id, "name": s.name, "serial": s.serial, "model": s.model, "certificate_number": s.certificate_number,
            "certificate_sha256": s.certificate_sha256, "calibrated_on": s.calibrated_on, "due_on": s.due_on,
            "uncertainty": s.uncertainty, "expanded_uncertainty_deg": s.expanded_uncertainty_deg,
            "coverage_factor": s.coverage_factor, "created_utc": s.created_at, "created_by": s.created_by,
            "status": "past_due" if days < 0 else ("due_soon" if days <= due_soon_days else "valid")}  # fmt: skip


@router.post("/standards", status_code=201)
def add_standard(body: StandardIn, request: Request, who: Admin) -> JSONResponse:
    """Register one certificate of a reference standard (scope admin). A recalibration is a new entry."""
    try:
        fields = body.model_dump()
        if "coverage_factor" not in body.model_fields_set:
            fields["coverage_factor"] = None if body.expanded_uncertainty_deg is None else 2.0
        row = _store(request).add_standard(fields, actor=who.name)
    except ConflictError as exc:
        raise ProblemError(409, "Standard already registered", str(exc)) from None
    s = request.app.state.settings
    return JSONResponse(_jsonable(standard_json(row, dt.datetime.now(dt.UTC).date(), s.standards_due_soon_days)),
                        status_code=201, headers={"Location": f"/standards/{row.id}"})


@router.get("/standards")
def list_standards(request: Request, _: Reader) -> dict:
    today, days = dt.datetime.now(dt.UTC).date(), request.app.state.settings.standards_due_soon_days
    return {"standards": [standard_json(s, today, days) for s in _store(request).standards()]}


@router.get("/standards/{standard_id}")
def read_standard(standard_id: int, request: Request, _: Reader) -> dict:
    try:
        row = _store(request).standard(standard_id)
    except UnknownEntity as exc:
        raise _not_found(exc) from None
    return standard_json(row, dt.datetime.now(dt.UTC).date(), request.app.state.settings.standards_due_soon_days)


# ---------------------------------------------------------------- approvals


class ApproveIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    meaning: Literal["approval", "review"] = Field("approval", description="what the signature means")
    note: str = Field("", max_length=10_000)


class RejectIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    reason: str = Field(min_length=1, max_length=10_000)


def approval_json(a: RecordApproval) -> dict[str, Any]:
    return {"id": a.id, "record_id": a.record_id, "decision": a.decision, "meaning": a.meaning, "note": a.note,
            "actor": a.actor, "time_utc": a.at, "record_sha256": a.record_sha256, "prev_sha256": a.prev_sha256,
            "sha256": a.sha256}  # fmt: skip


def _decide(request: Request, record_id: int, actor: str, **kw: Any) -> dict[str, Any]:
    store = _store(request)
    try:
        row = store.decide(record_id, actor=actor, **kw)
    except UnknownEntity as exc:
        raise _not_found(exc) from None
    except SelfApproval as exc:
        raise ProblemError(403, "Segregation of duties", str(exc)) from None
    except ConflictError as exc:
        raise ProblemError(409, "Decision already made", str(exc)) from None
    # the bench's record in use follows the decision: its status, or (rejected) withdrawn
    jobs = getattr(request.app.state, "jobs", None)  # none in a LIMS-only application
    if jobs is not None and (bench := jobs.bench_of_device(store.get_record(record_id).device_id)) is not None:
        jobs.load_active(bench)
    return {"approval": approval_json(row), "record": {"id": record_id, "status": store.record_status(record_id)}}


@router.post("/records/{record_id}/approve")
def approve(record_id: int, body: ApproveIn, request: Request, who: Admin) -> dict:
    """Sign a draft record (scope admin): meaning `approval` makes it approved, `review` records a review.
    Refused (403) to the token that started the record's job or ran it."""
    return _decide(request, record_id, who.name, decision="approve", meaning=body.meaning, note=body.note)


@router.post("/records/{record_id}/reject")
def reject(record_id: int, body: RejectIn, request: Request, who: Admin) -> dict:
    """Reject a draft record with a reason (scope admin; not by the token that started its job: 403)."""
    return _decide(request, record_id, who.name, decision="reject", meaning="rejection", note=body.reason)


@router.get("/records/{record_id}/approvals")
def approvals(record_id: int, request: Request, _: Reader) -> dict:
    store = _store(request)
    try:
        store.get_record(record_id)
    except UnknownEntity as exc:
        raise _not_found(exc) from None
    rows = store.approvals(record_id)
    return {"record_id": record_id, "status": store.status_of(rows), "approvals": [approval_json(a) for a in rows]}


# ---------------------------------------------------------------- certificates


def _certificate(request: Request, record_id: int, actor: str):  # type: ignore[no-untyped-def]
    try:
        return issue_certificate(_store(request), record_id, request.app.state.settings, actor=actor)
    except UnknownEntity as exc:
        raise _not_found(exc) from None
    except NotApproved as exc:
        raise ProblemError(409, "Record not approved", str(exc)) from None
    except NotConfigured as exc:
        raise ProblemError(503, "Laboratory not configured", str(exc)) from None
    except IntegrityFailure as exc:
        raise ProblemError(500, "Integrity failure", str(exc)) from None
    except dcc.InvalidCertificate as exc:
        raise ProblemError(500, "Certificate not issued", f"the certificate would not be valid, so none was issued: {exc}") from None


@router.get("/records/{record_id}/certificate", response_class=Response, responses=_XML)
def certificate(record_id: int, request: Request, who: Reader) -> Response:
    """The DCC 3.3.0 certificate of an approved record (409 for a draft or rejected one). Issued on first
    request, validated against the schema first, then stored with its SHA-256 and always served as stored."""
    cert = _certificate(request, record_id, who.name)
    return Response(cert.xml, media_type="application/xml", headers={
        "Content-Disposition": f'attachment; filename="{cert.number}.xml"', "X-Certificate-SHA256": cert.sha256})


@router.get("/records/{record_id}/certificate.html", response_class=HTMLResponse)
def certificate_html(record_id: int, request: Request, who: Reader) -> HTMLResponse:
    """The same certificate as a printable page for people."""
    cert = _certificate(request, record_id, who.name)
    return HTMLResponse(dcc.render_html(cert.xml))


# ---------------------------------------------------------------- orders


class CustomerIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(max_length=200)
    city: str = Field(max_length=200)
    country_code: str = Field(pattern=r"^[A-Z]{2}$", description="ISO 3166-1 alpha-2")
    street: str | None = Field(None, max_length=200)
    post_code: str | None = Field(None, max_length=20)
    email: str | None = Field(None, max_length=200)


class OrderIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    lims_order_id: str = Field(max_length=100)
    item_serial: str = Field(max_length=100)
    item_manufacturer: str | None = Field(None, max_length=100, description="the item's manufacturer (its certificate names it)")
    item_model: str | None = Field(None, max_length=100, description="the item's model (its certificate names it)")
    customer: CustomerIn
    procedure: Literal["stage-grid", "scale", "rotation", "turntable"]
    method: str = Field(max_length=80)
    due_on: dt.date | None = None


def order_json(request: Request, o: Order) -> dict[str, Any]:
    links = _store(request).order_links(o.id)
    return {"id": o.id, "lims_order_id": o.lims_order_id, "item_serial": o.item_serial,
            "item_manufacturer": o.item_manufacturer, "item_model": o.item_model, "customer": o.customer,
            "procedure": o.procedure, "method": o.method, "due_on": o.due_on, "created_utc": o.created_at,
            "created_by": o.created_by, **links}  # fmt: skip


@router.post("/orders", status_code=201)
def create_order(body: OrderIn, request: Request, who: Operator,
                 idempotency_key: Annotated[str | None, Header(max_length=200)] = None) -> JSONResponse:
    """Create an order (scope operate). With an `Idempotency-Key`, a repeat returns the first order (200);
    the same key with another body is 422."""
    try:
        row, created = _store(request).create_order(body.model_dump(mode="json", exclude_none=True), actor=who.name,
                                                    idempotency_key=idempotency_key)
    except ConflictError as exc:
        raise ProblemError(409, "Order exists", str(exc), field="lims_order_id") from None
    return JSONResponse(_jsonable(order_json(request, row)), status_code=201 if created else 200,
                        headers={"Location": f"/orders/{row.id}"})


@router.get("/orders/{order_id}")
def read_order(order_id: int, request: Request, _: Reader) -> dict:
    """The order, its jobs, records (with status) and certificates, and its state: open, in_progress,
    measured, approved, rejected, certified or failed."""
    try:
        row = _store(request).order(order_id)
    except UnknownEntity as exc:
        raise _not_found(exc) from None
    return order_json(request, row)


# ---------------------------------------------------------------- the feed


@router.get("/feed")
def feed(request: Request, _: Reader, cursor: Annotated[str | None, Query(max_length=100)] = None,
         limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> dict:
    """Events oldest first from after `cursor` (none: from the start). Hand `next_cursor` back on the next
    poll: a client that does never misses or repeats an event, even while events are being written."""
    after = decode_cursor(cursor)
    events = _store(request).feed(after_id=after, limit=limit)
    return {"events": [event_json(e) for e in events],
            "next_cursor": encode_cursor(events[-1].id if events else after)}


# ---------------------------------------------------------------- webhooks


class WebhookIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    url: str = Field(max_length=2000, examples=["https://lims.example.org/tiltlab-hook"])
    events: list[str] = Field(min_length=1, description=f"event types ({', '.join(EVENT_TYPES)}) or ['*'] for all")


@router.post("/webhooks", status_code=201)
def add_webhook(body: WebhookIn, request: Request, who: Admin) -> JSONResponse:
    """Register an endpoint (scope admin). The answer carries its signing `secret`, shown this once."""
    row, secret = _store(request).add_webhook(body.url, body.events, actor=who.name)
    dispatcher = getattr(request.app.state, "webhooks", None)
    if dispatcher is not None:
        dispatcher.wake.set()
    return JSONResponse(_jsonable({"id": row.id, "url": row.url, "events": row.events, "secret": secret,
                                   "created_utc": row.created_at}),
                        status_code=201, headers={"Location": f"/webhooks/{row.id}"})  # fmt: skip


@router.get("/webhooks")
def list_webhooks(request: Request, _: Admin) -> dict:
    return {"webhooks": [{"id": w.id, "url": w.url, "events": w.events, "created_utc": w.created_at,
                          "created_by": w.created_by} for w in _store(request).webhooks()]}  # fmt: skip


@router.get("/webhooks/{webhook_id}/deliveries")
def deliveries(webhook_id: int, request: Request, _: Admin,
               limit: Annotated[int, Query(ge=1, le=1000)] = 200) -> dict:
    """The delivery log, newest first: each event's state (pending, delivered, failed) and every attempt."""
    store = _store(request)
    try:
        store.webhook(webhook_id)
    except UnknownEntity as exc:
        raise _not_found(exc) from None
    return {"webhook_id": webhook_id, "deliveries": [
        {"id": d.id, "event_id": event_json(e)["id"], "event_type": e.type, "state": d.state, "attempts": d.attempts,
         "next_attempt_utc": d.next_attempt_at, "delivered_utc": d.delivered_at, "last_status_code": d.last_status_code,
         "last_error": d.last_error,
         "log": [{"time_utc": a.at, "status_code": a.status_code, "error": a.error, "duration_s": a.duration_s}
                 for a in attempts]}
        for d, e, attempts in store.deliveries(webhook_id, limit=limit)]}  # fmt: skip


def _jsonable(value: Any) -> Any:
    from fastapi.encoders import jsonable_encoder

    return jsonable_encoder(value)
