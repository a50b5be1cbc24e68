"""The LIMS event feed and the webhook outbox, written in the transaction of the change they report.

Every state change already writes an audit event inside the store's serialised write
transaction; `append_for_audit` turns the ones a LIMS cares about into a feed event in that same
transaction, and queues one webhook delivery per subscribed endpoint. Because write transactions
are serialised, feed ids grow in commit order: a reader that has seen id n has seen every event
before it, so paging by id never misses or repeats one, even while events are being written.
"""

from __future__ import annotations

import base64
import binascii
from collections.abc import Mapping
from typing import TypedDict

import sqlalchemy as sa
from sqlalchemy.orm import Session

from service.errors import InputError
from service.storage.models import (
    AuditEvent,
    CalibrationJob,
    CalibrationRecord,
    FeedEvent,
    WebhookDelivery,
    WebhookEndpoint,
)

EVENT_TYPES = (
    "job.state",
    "record.created",
    "record.reviewed",
    "record.approved",
    "record.rejected",
    "record.activated",
    "certificate.issued",
    "standard.due_soon",
    "order.created",
    "diagnosis.finished",
)
_JOB_STATES = ("queued", "running", "succeeded", "failed", "cancelled")
# an audit event's hashes of the rows it changed (service/storage/rowhash.py)
ROW_ANCHORS = "rows_sha256"


class JobStateData(TypedDict):
    """The data of a `job.state` event."""

    job_id: int
    state: str
    previous_state: str | None
    failure_reason: str | None
    order_id: int | None
    bench_id: int | None


class FeedEventJson(TypedDict):
    """An event as the feed and the webhooks show it."""

    id: str
    type: str
    time_utc: str
    # a job.state event's JobStateData, a record event's record facts and the action's own keys,
    # or the audit details of the other actions
    data: Mapping[str, object]


def _job_event(session: Session, audit_event: AuditEvent, state: str) -> JobStateData:
    job = session.get(CalibrationJob, int(audit_event.entity_id))
    return {
        "job_id": int(audit_event.entity_id),
        "state": state,
        "previous_state": audit_event.details.get("from"),
        "failure_reason": audit_event.details.get("failure_reason"),
        "order_id": job.order_id if job else None,
        "bench_id": job.bench_id if job else None,
    }


def _record_event(
    session: Session, record_id: int, extra: Mapping[str, object]
) -> dict[str, object]:
    record = session.get(CalibrationRecord, record_id)
    job = (
        session.get(CalibrationJob, record.job_id)
        if record is not None and record.job_id is not None
        else None
    )
    base: dict[str, object] = {"record_id": record_id}
    if record is not None:
        base.update(
            {
                "device_id": record.device_id,
                "kind": record.kind,
                "version": record.version,
                "method": record.method,
                "content_sha256": record.content_sha256,
                "job_id": record.job_id,
                "order_id": job.order_id if job else None,
            }
        )
    return {**base, **extra}


# the job state each job action reports
_JOB_ACTION_STATES = {
    "job.create": "queued",
    **{f"job.{state}": state for state in _JOB_STATES},
    "job.resume": "running",
}
# record decisions (review, approval, rejection) and the details their feed events carry
_DECISION_EVENTS = {
    "record.review": "record.reviewed",
    "record.approve": "record.approved",
    "record.reject": "record.rejected",
}
_DECISION_KEYS = ("approval_id", "actor", "signer", "meaning", "note", "record_sha256")
# actions reported with their audit details as they are
_PLAIN_EVENTS = {
    "diagnosis.finish": "diagnosis.finished",
    "certificate.issue": "certificate.issued",
    "standard.due_soon": "standard.due_soon",
    "order.create": "order.created",
}


def _record_feed_event(
    session: Session, audit_event: AuditEvent
) -> tuple[str, dict[str, object]] | None:
    """The feed event of a record's creation, activation or decision; None for other actions."""
    action, details = audit_event.action, audit_event.details
    if action == "record.create":
        return "record.created", _record_event(session, int(audit_event.entity_id), {})
    if action == "pointer.set":
        return "record.activated", _record_event(
            session,
            int(details["record_id"]),
            {"previous_record_id": details.get("previous_record_id")},
        )
    kind = _DECISION_EVENTS.get(action)
    if kind is None:
        return None
    return kind, _record_event(
        session, int(audit_event.entity_id), {key: details.get(key) for key in _DECISION_KEYS}
    )


def event_for(session: Session, audit_event: AuditEvent) -> tuple[str, Mapping[str, object]] | None:
    """The feed event (type, data) an audit event stands for, or None if a LIMS need not hear of
    it."""
    job_state = _JOB_ACTION_STATES.get(audit_event.action)
    if job_state is not None:
        return "job.state", _job_event(session, audit_event, job_state)
    record_event = _record_feed_event(session, audit_event)
    if record_event is not None:
        return record_event
    # the rows' hashes are the audit chain's, not news
    data = {key: value for key, value in audit_event.details.items() if key != ROW_ANCHORS}
    kind = _PLAIN_EVENTS.get(audit_event.action)
    return None if kind is None else (kind, data)


def append_for_audit(session: Session, audit_event: AuditEvent) -> FeedEvent | None:
    """Called for every audit event inside its transaction: the feed event and its outbox rows."""
    found = event_for(session, audit_event)
    if found is None:
        return None
    kind, data = found
    event = FeedEvent(type=kind, at=audit_event.at, data=data, audit_event_id=audit_event.id)
    session.add(event)
    session.flush()
    endpoints = session.execute(
        sa.select(WebhookEndpoint.id, WebhookEndpoint.events).where(
            WebhookEndpoint.disabled_at.is_(None)
        )
    )
    for endpoint_id, events in endpoints:
        if "*" in events or kind in events:
            session.add(
                WebhookDelivery(
                    endpoint_id=endpoint_id,
                    event_id=event.id,
                    state="pending",
                    attempts=0,
                    next_attempt_at=audit_event.at,
                    created_at=audit_event.at,
                )
            )
    return event


def event_json(event: FeedEvent) -> FeedEventJson:
    """An event as the feed and the webhooks show it."""
    return {
        "id": event_id(event.id),
        "type": event.type,
        "time_utc": event.at.strftime("%Y-%m-%dT%H:%M:%S.%fZ"),
        "data": event.data,
    }


def event_id(n: int) -> str:
    return f"evt_{n}"


# ---------------------------------------------------------------- cursors

_CURSOR_PREFIX = "f1."


def encode_cursor(last_id: int) -> str:
    """Opaque to clients: they only hand it back."""
    return _CURSOR_PREFIX + base64.urlsafe_b64encode(str(last_id).encode()).decode().rstrip("=")


def decode_cursor(cursor: str | None) -> int:
    if cursor is None or cursor == "":
        return 0
    try:
        if not cursor.startswith(_CURSOR_PREFIX):
            raise ValueError
        body = cursor.removeprefix(_CURSOR_PREFIX)
        value = int(base64.urlsafe_b64decode(body + "=" * (-len(body) % 4)).decode("ascii"))
        if value < 0:
            raise ValueError
        return value
    except (ValueError, binascii.Error, UnicodeDecodeError):
        raise InputError(
            f"cursor {cursor[:40]!r} is not a cursor this feed gave out; start without one"
        ) from None
