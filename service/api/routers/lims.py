"""LIMS integration over HTTP: reference standards, approvals, certificates, orders, the event feed,
webhooks."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, TypedDict

from fastapi import APIRouter, Header, Query
from fastapi.responses import HTMLResponse, Response

from service.api.auth import Admin, Operator, Reader
from service.api.deps import (
    ApprovalsRepoDep,
    FeedRepoDep,
    JobsIfAnyDep,
    OrderId,
    RecordId,
    RecordsRepoDep,
    SettingsDep,
    StandardId,
    StandardsRepoDep,
    StoreDep,
    WebhookId,
    WebhooksDep,
    WebhooksRepoDep,
)
from service.api.models.lims import (
    Approvals,
    ApproveIn,
    Decision,
    Deliveries,
    Feed,
    NewWebhook,
    Order,
    OrderIn,
    RejectIn,
    Standard,
    StandardIn,
    Standards,
    Webhook,
    WebhookIn,
    Webhooks,
)
from service.api.models.paging import CURSOR, DEFAULT_PAGE, LIMIT, MAX_PAGE, json_answer
from service.api.models.problem import READ, WRITE, problem_responses
from service.api.offloop import off_loop
from service.api.problems import ProblemError
from service.config import Settings
from service.errors import InputError
from service.jobs.manager import JobManager
from service.jobs.requests import DB_ID_MAX
from service.lims import dcc
from service.lims.certificates import (
    CertificateRefused,
    IntegrityFailure,
    NotApproved,
    NotConfigured,
    issue_certificate,
    record_conformity,
)
from service.storage.errors import ConflictError
from service.storage.feed import decode_cursor, encode_cursor, event_json
from service.storage.models import Certificate, RecordApproval, ReferenceStandard
from service.storage.models import Order as OrderRow
from service.storage.specification import SpecificationProblem
from service.storage.store import ApprovalsRepo, RecordsRepo, Store
from service.storage.store.approvals import SelfApproval, signer_of
from service.storage.store.webhooks import shown_url
from service.storage.tokens import Person, Principal

router = APIRouter(tags=["lims"])


FEED_ID_MAX = 2**63 - 1  # feed event ids are BIGINT


class XMLResponse(Response):
    media_type = "application/xml"


# ---------------------------------------------------------------- reference standards


def standard_body(s: ReferenceStandard, today: dt.date, due_soon_days: int) -> Standard:
    days = (s.due_on - today).days
    return Standard.model_validate(
        {
            "id": s.id,
            "name": s.name,
            "serial": s.serial,
            "model": s.model,
            "certificate_number": s.certificate_number,
            "certificate_sha256": s.certificate_sha256,
            "calibrated_on": s.calibrated_on,
            "due_on": s.due_on,
            "uncertainty": s.uncertainty,
            "expanded_uncertainty_deg": s.expanded_uncertainty_deg,
            "coverage_factor": s.coverage_factor,
            "created_utc": s.created_at,
            "created_by": s.created_by,
            "status": "past_due"
            if days < 0
            else ("due_soon" if days <= due_soon_days else "valid"),
            "calibrated_by": s.calibrated_by,
        }
    )


def _today() -> dt.date:
    return dt.datetime.now(dt.UTC).date()


@router.post(
    "/standards", status_code=201, response_model=Standard, responses=problem_responses(*WRITE, 409)
)
@off_loop
def add_standard(
    body: StandardIn,
    response: Response,
    standards: StandardsRepoDep,
    settings: SettingsDep,
    who: Admin,
) -> Standard:
    """Register one certificate of a reference standard (scope admin). A recalibration is a new
    entry."""
    try:
        fields = body.model_dump(exclude={"calibrated_by"})
        if body.calibrated_by is not None:
            fields["calibrated_by"] = body.calibrated_by.model_dump(exclude_none=True)
        if "coverage_factor" not in body.model_fields_set:
            fields["coverage_factor"] = None if body.expanded_uncertainty_deg is None else 2.0
        row = standards.add_standard(fields, actor=who.name)
    except ConflictError as exc:
        raise ProblemError(409, "Standard already registered", str(exc)) from None
    response.headers["Location"] = f"/standards/{row.id}"
    return standard_body(row, _today(), settings.standards_due_soon_days)


@router.get("/standards", response_model=Standards, responses=problem_responses(*READ))
@off_loop
def list_standards(
    standards: StandardsRepoDep,
    settings: SettingsDep,
    _: Reader,
    cursor: Annotated[int | None, Query(ge=1, le=DB_ID_MAX, description=CURSOR)] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE, description=LIMIT)] = DEFAULT_PAGE,
) -> Response:
    """Reference standards in the order they were registered, a page at a time (`next_cursor` pages
    on)."""
    today, days = _today(), settings.standards_due_soon_days
    rows = standards.page(after_id=cursor, limit=limit)
    return json_answer(
        Standards(
            standards=[standard_body(standard, today, days) for standard in rows],
            next_cursor=rows[-1].id if len(rows) == limit else None,
        )
    )


@router.get(
    "/standards/{standard_id}", response_model=Standard, responses=problem_responses(*READ, 404)
)
@off_loop
def read_standard(
    standard_id: StandardId, standards: StandardsRepoDep, settings: SettingsDep, _: Reader
) -> Standard:
    return standard_body(standards.get(standard_id), _today(), settings.standards_due_soon_days)


# ---------------------------------------------------------------- approvals


class SignerBody(TypedDict):
    """The person who signed a decision, as its body names them."""

    name: str
    function: str | None


class ApprovalBody(TypedDict):
    """A review decision on a record as the API states it (`Approval`)."""

    id: int
    record_id: int
    decision: str
    meaning: str
    note: str
    actor: str
    signer: SignerBody | None
    time_utc: dt.datetime
    record_sha256: str
    prev_sha256: str
    sha256: str


def approval_body(a: RecordApproval) -> ApprovalBody:
    person = signer_of(a)
    return {
        "id": a.id,
        "record_id": a.record_id,
        "decision": a.decision,
        "meaning": a.meaning,
        "note": a.note,
        "actor": a.actor,
        "signer": {"name": person.name, "function": person.function} if person else None,
        "time_utc": a.at,
        "record_sha256": a.record_sha256,
        "prev_sha256": a.prev_sha256,
        "sha256": a.sha256,
    }


def signer(who: Principal) -> Person:
    """The person who signs with this token: a name and a function (17025 7.8.2.1 o); 403 naming
    what is missing."""
    fix = (
        f'PATCH /tokens/{who.name} {{"person": {{"name": ..., "function": ...}}}} (or tiltlab '
        "token "
        f"set-person {who.name} --person-name ... --person-function ...)"
    )
    if who.person is None:
        raise ProblemError(
            403,
            "No person behind the token",
            f"the token {who.name!r} names no person; a record is approved or rejected by a "
            f"person, with a name and a function, whom its certificate names: {fix}",
        )
    if not who.person.function:
        raise ProblemError(
            403,
            "No function of the person",
            f"the token {who.name!r} names {who.person.name} but not their function, which a "
            f"certificate states for who authorised it: {fix}",
        )
    return who.person


def _decide(
    approvals: ApprovalsRepo,
    records: RecordsRepo,
    jobs: JobManager | None,
    record_id: int,
    who: Principal,
    **kw: Any,
) -> Decision:
    person = signer(who)
    try:
        row = approvals.decide(record_id, actor=who.name, signer=person, **kw)
    except SelfApproval as exc:
        raise ProblemError(403, "Segregation of duties", str(exc)) from None
    except ConflictError as exc:
        raise ProblemError(409, "Decision already made", str(exc)) from None
    # the bench's record in use follows the decision: its status, or (rejected) withdrawn
    if (
        jobs is not None
        and (bench := jobs.bench_of_device(records.get_record(record_id).device_id)) is not None
    ):
        jobs.load_active(bench)
    return Decision.model_validate(
        {
            "approval": approval_body(row),
            "record": {"id": record_id, "status": approvals.record_status(record_id)},
        }
    )


@router.post(
    "/records/{record_id}/approve",
    response_model=Decision,
    responses=problem_responses(*WRITE, 404, 409),
)
@off_loop
def approve(
    record_id: RecordId,
    body: ApproveIn,
    approvals: ApprovalsRepoDep,
    records: RecordsRepoDep,
    jobs: JobsIfAnyDep,
    who: Admin,
) -> Decision:
    """Sign a draft record (scope admin): meaning `approval` makes it approved, `review` records a
    review. The token must name its person, with a function (403 otherwise): the approval keeps who
    signed, and the certificate names them as its main signer. Refused (403) to the token that
    started the record's job or ran it."""
    return _decide(
        approvals,
        records,
        jobs,
        record_id,
        who,
        decision="approve",
        meaning=body.meaning,
        note=body.note,
    )


@router.post(
    "/records/{record_id}/reject",
    response_model=Decision,
    responses=problem_responses(*WRITE, 404, 409),
)
@off_loop
def reject(
    record_id: RecordId,
    body: RejectIn,
    approvals: ApprovalsRepoDep,
    records: RecordsRepoDep,
    jobs: JobsIfAnyDep,
    who: Admin,
) -> Decision:
    """Reject a draft record with a reason (scope admin, by a token that names its person; not by
    the token that started its job: 403)."""
    return _decide(
        approvals,
        records,
        jobs,
        record_id,
        who,
        decision="reject",
        meaning="rejection",
        note=body.reason,
    )


@router.get(
    "/records/{record_id}/approvals",
    response_model=Approvals,
    responses=problem_responses(*READ, 404),
)
@off_loop
def approvals(
    record_id: RecordId,
    approvals: ApprovalsRepoDep,
    records: RecordsRepoDep,
    _: Reader,
    cursor: Annotated[int | None, Query(ge=1, le=DB_ID_MAX, description=CURSOR)] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE, description=LIMIT)] = DEFAULT_PAGE,
) -> Approvals:
    """The record's reviews, approvals and rejections, oldest first, a page at a time (`next_cursor`
    pages on); `status` is the record's, from all of them."""
    records.get_record(record_id)
    rows = approvals.of_record(record_id)
    page = [approval for approval in rows if cursor is None or approval.id > cursor][:limit]
    return Approvals.model_validate(
        {
            "record_id": record_id,
            "status": approvals.status_of(rows),
            "approvals": [approval_body(approval) for approval in page],
            "next_cursor": page[-1].id if len(page) == limit else None,
        }
    )


# ---------------------------------------------------------------- certificates


def _certificate(store: Store, record_id: int, settings: Settings, actor: str) -> Certificate:
    try:
        return issue_certificate(store, record_id, settings, actor=actor)
    except NotApproved as exc:
        raise ProblemError(409, "Record not approved", str(exc)) from None
    except CertificateRefused as exc:
        raise ProblemError(409, "Record cannot be certified", str(exc)) from None
    except NotConfigured as exc:
        raise ProblemError(503, "Laboratory not configured", str(exc)) from None
    except IntegrityFailure as exc:
        raise ProblemError(500, "Integrity failure", str(exc)) from None
    except dcc.InvalidCertificate as exc:
        raise ProblemError(
            500,
            "Certificate not issued",
            f"the certificate would not be valid, so none was issued: {exc}",
        ) from None


_CERTIFICATE_ERRORS = problem_responses(*READ, 404, 409, 503)


@router.get(
    "/records/{record_id}/certificate",
    response_class=XMLResponse,
    responses={
        200: {
            "description": "the DCC 3.3.0 certificate (Digital Calibration Certificate, PTB's XML "
            "schema dcc.xsd 3.3.0)",
            "content": {
                "application/xml": {
                    "schema": {"type": "string", "contentMediaType": "application/xml"}
                }
            },
        },
        **_CERTIFICATE_ERRORS,
    },
)
@off_loop
def certificate(
    record_id: RecordId, store: StoreDep, settings: SettingsDep, who: Reader
) -> XMLResponse:
    """The DCC 3.3.0 certificate of an approved record (409 for a draft or rejected one, and for a
    record that cannot be certified: calibrated without a registered reference standard valid on the
    day, or a standard that does not name who calibrated it; approved by a token without a person).
    Issued on first request, validated against the schema first, then stored with its SHA-256 and
    always served as stored."""
    cert = _certificate(store, record_id, settings, who.name)
    return XMLResponse(
        cert.xml,
        headers={
            "Content-Disposition": f'attachment; filename="{cert.number}.xml"',
            "X-Certificate-SHA256": cert.sha256,
        },
    )


@router.get(
    "/records/{record_id}/certificate.html",
    response_class=HTMLResponse,
    responses={
        200: {
            "description": "the certificate as a printable page",
            "content": {"text/html": {"schema": {"type": "string"}}},
        },
        **_CERTIFICATE_ERRORS,
    },
)
@off_loop
def certificate_html(
    record_id: RecordId, store: StoreDep, settings: SettingsDep, who: Reader
) -> HTMLResponse:
    """The same certificate as a printable page for people."""
    cert = _certificate(store, record_id, settings, who.name)
    return HTMLResponse(dcc.render_html(cert.xml))


# ---------------------------------------------------------------- orders


def order_body(store: Store, o: OrderRow) -> Order:
    links = store.orders.order_links(o.id)
    conformity = None
    if o.specification and links["records"]:
        conformity = record_conformity(store, store.records.get_record(links["records"][-1]["id"]))
    return Order.model_validate(
        {
            "id": o.id,
            "lims_order_id": o.lims_order_id,
            "item_serial": o.item_serial,
            "item_manufacturer": o.item_manufacturer,
            "item_model": o.item_model,
            "customer": o.customer,
            "procedure": o.procedure,
            "method": o.method,
            "due_on": o.due_on,
            "created_utc": o.created_at,
            "created_by": o.created_by,
            "specification": o.specification,
            "conformity": conformity,
            **links,
        }
    )


@router.post(
    "/orders",
    status_code=201,
    response_model=Order,
    responses={
        200: {
            "model": Order,
            "description": "A repeat of an earlier request's Idempotency-Key: that request's order",
        },
        **problem_responses(*WRITE, 409),
    },
)
@off_loop
def create_order(
    body: OrderIn,
    response: Response,
    store: StoreDep,
    who: Operator,
    idempotency_key: Annotated[str | None, Header(max_length=200)] = None,
) -> Order:
    """Create an order (scope operate). With an `Idempotency-Key`, a repeat returns the first order
    (200); the same key with another body is 422. A `specification` (stage-grid orders) makes the
    certificate state conformity with it."""
    try:
        row, created = store.orders.create_order(
            body.model_dump(mode="json", exclude_none=True),
            actor=who.name,
            idempotency_key=idempotency_key,
        )
    except ConflictError as exc:
        raise ProblemError(409, "Order exists", str(exc), field="lims_order_id") from None
    except SpecificationProblem as exc:
        raise ProblemError(422, "Unusable specification", str(exc), field=exc.field) from None
    response.headers["Location"] = f"/orders/{row.id}"
    if not created:
        response.status_code = 200
    return order_body(store, row)


@router.get("/orders/{order_id}", response_model=Order, responses=problem_responses(*READ, 404))
@off_loop
def read_order(order_id: OrderId, store: StoreDep, _: Reader) -> Order:
    """The order, its jobs, records (with status) and certificates, and its state: open,
    in_progress, measured, approved, rejected, certified or failed; with a specification, the newest
    record's statements of conformity."""
    return order_body(store, store.orders.get(order_id))


# ---------------------------------------------------------------- the feed


@router.get("/feed", response_model=Feed, responses=problem_responses(*READ))
@off_loop
def feed(
    feed_events: FeedRepoDep,
    _: Reader,
    cursor: Annotated[
        str | None,
        Query(
            max_length=100,
            pattern=r"^(f1\.[A-Za-z0-9_-]*)?$",
            description="`next_cursor` of the previous poll (opaque)",
        ),
    ] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> Response:
    """Events oldest first from after `cursor` (none: from the start). Hand `next_cursor` back on
    the next poll: a client that does never misses or repeats an event, even while events are being
    written."""
    try:
        after = decode_cursor(cursor)
    except InputError as exc:
        raise ProblemError(422, "Invalid request", f"cursor: {exc}", field="cursor") from None
    if after > FEED_ID_MAX:
        raise ProblemError(
            422,
            "Invalid request",
            "cursor: not a cursor this feed gave out; start without one",
            field="cursor",
        )
    events = feed_events.events(after_id=after, limit=limit)
    return json_answer(
        Feed.model_validate(
            {
                "events": [event_json(event) for event in events],
                "next_cursor": encode_cursor(events[-1].id if events else after),
            }
        )
    )


# ---------------------------------------------------------------- webhooks


@router.post(
    "/webhooks", status_code=201, response_model=NewWebhook, responses=problem_responses(*WRITE)
)
@off_loop
def add_webhook(
    body: WebhookIn,
    response: Response,
    webhooks: WebhooksRepoDep,
    dispatcher: WebhooksDep,
    who: Admin,
) -> NewWebhook:
    """Register an endpoint (scope admin). The answer carries its signing `secret`, shown this
    once."""
    row, secret = webhooks.add_webhook(body.url, body.events, actor=who.name)
    if dispatcher is not None:
        dispatcher.nudge()
    response.headers["Location"] = f"/webhooks/{row.id}"
    return NewWebhook(
        id=row.id, url=row.url, events=row.events, secret=secret, created_utc=row.created_at
    )


@router.get("/webhooks", response_model=Webhooks, responses=problem_responses(*READ))
@off_loop
def list_webhooks(
    webhooks: WebhooksRepoDep,
    _: Admin,
    cursor: Annotated[int | None, Query(ge=1, le=DB_ID_MAX, description=CURSOR)] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE, description=LIMIT)] = DEFAULT_PAGE,
) -> Response:
    """Webhook endpoints in the order they were registered, a page at a time (`next_cursor` pages
    on). A URL stored with credentials in it (before they were refused) is shown without them."""
    rows = webhooks.page(after_id=cursor, limit=limit)
    return json_answer(
        Webhooks(
            webhooks=[
                Webhook(
                    id=webhook.id,
                    url=shown_url(webhook.url),
                    events=webhook.events,
                    created_utc=webhook.created_at,
                    created_by=webhook.created_by,
                )
                for webhook in rows
            ],
            next_cursor=rows[-1].id if len(rows) == limit else None,
        )
    )


@router.get(
    "/webhooks/{webhook_id}/deliveries",
    response_model=Deliveries,
    responses=problem_responses(*READ, 404),
)
@off_loop
def deliveries(
    webhook_id: WebhookId,
    webhooks: WebhooksRepoDep,
    _: Admin,
    cursor: Annotated[int | None, Query(ge=1, le=FEED_ID_MAX, description=CURSOR)] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE, description=LIMIT)] = DEFAULT_PAGE,
) -> Response:
    """The delivery log, newest first: each event's state (pending, delivered, failed) and every
    attempt, a page at a time (`next_cursor` pages on)."""
    webhooks.get(webhook_id)
    found = webhooks.deliveries(webhook_id, before_id=cursor, limit=limit)
    return json_answer(
        Deliveries.model_validate(
            {
                "webhook_id": webhook_id,
                "next_cursor": found[-1][0].id if len(found) == limit else None,
                "deliveries": [
                    {
                        "id": delivery.id,
                        "event_id": event_json(event)["id"],
                        "event_type": event.type,
                        "state": delivery.state,
                        "attempts": delivery.attempts,
                        "next_attempt_utc": delivery.next_attempt_at,
                        "delivered_utc": delivery.delivered_at,
                        "last_status_code": delivery.last_status_code,
                        "last_error": delivery.last_error,
                        "log": [
                            {
                                "time_utc": attempt.at,
                                "status_code": attempt.status_code,
                                "error": attempt.error,
                                "duration_s": attempt.duration_s,
                            }
                            for attempt in attempts
                        ],
                    }
                    for delivery, event, attempts in found
                ],
            }
        )
    )
