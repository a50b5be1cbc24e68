"""What the LIMS integration keeps: reference standards, orders, approvals, issued certificates,
the event feed and the webhook outbox. Every write is one serialised transaction with its audit event
(and so its feed event: see feed.py)."""

from __future__ import annotations

import base64
import datetime as dt
import hashlib
import math
import re
import secrets
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

import sqlalchemy as sa

from service.errors import InputError
from service.storage.canonical import normalise, sha256_hex, utc_iso
from service.storage.errors import ConflictError, RefusedWrite, UnknownEntity
from service.storage.feed import EVENT_TYPES
from service.storage.models import (
    GENESIS_SHA256,
    ActiveCalibration,
    CalibrationJob,
    CalibrationRecord,
    Certificate,
    FeedEvent,
    Order,
    RecordApproval,
    ReferenceStandard,
    WebhookAttempt,
    WebhookDelivery,
    WebhookEndpoint,
    utc_now,
)
from service.storage.stated_uncertainty import parse_stated_uncertainty
from service.storage.store.activation import ActivationStore
from service.storage.store.checks import _text
from service.storage.store.hashing import record_content

_SHA256 = re.compile(r"[0-9a-f]{64}")
APPROVE_MEANINGS = ("review", "approval")


class StandardNotUsable(InputError):
    """A job names a reference standard past its due date (or one that does not exist); `field` says which."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f"{field}: {reason}")
        self.field, self.reason = field, reason


class SelfApproval(RefusedWrite):
    """Segregation of duties: the one who started the job (or ran it) may not approve or reject its record."""


class IdempotencyKeyReused(InputError):
    """The same Idempotency-Key came with another body."""


def approval_content(a: RecordApproval) -> dict[str, Any]:
    """What an approval asserts; its SHA-256 is `sha256` (canonical rule of canonical.py)."""
    return {"record_id": a.record_id, "decision": a.decision, "meaning": a.meaning, "note": a.note,
            "actor": a.actor, "at": utc_iso(a.at), "record_sha256": a.record_sha256, "prev_sha256": a.prev_sha256}


def _date(name: str, value: object) -> dt.date:
    if isinstance(value, dt.datetime):
        raise InputError(f"{name}: a date (YYYY-MM-DD) is needed, not a time")
    if isinstance(value, dt.date):
        return value
    if isinstance(value, str):
        try:
            return dt.date.fromisoformat(value)
        except ValueError:
            pass
    raise InputError(f"{name}: {value!r} is not a date (YYYY-MM-DD)")


def _number(name: str, value: object, *, above: float | None = None, least: float | None = None) -> float:
    ok = not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value) \
        and (above is None or value > above) and (least is None or value >= least)
    if not ok:
        raise InputError(f"{name}: {value!r} is not a number {f'> {above:g}' if above is not None else f'>= {least:g}'}")
    return float(value)  # type: ignore[arg-type]


def _stated_uncertainty(fields: Mapping[str, Any], remark: str) -> tuple[float | None, float | None]:
    """U (degrees) and k as given, else read from the remark's wording; (None, None) when neither says."""
    U, k = fields.get("expanded_uncertainty_deg"), fields.get("coverage_factor")
    if U is None:
        if k is not None:
            raise InputError("coverage_factor: given without expanded_uncertainty_deg")
        parsed = parse_stated_uncertainty(remark)
        return parsed if parsed is not None else (None, None)
    return (_number("expanded_uncertainty_deg", U, above=0.0),
            _number("coverage_factor", 2.0 if k is None else k, least=1.0))


def webhook_url(url: object) -> str:
    """An http(s) URL with a host; anything else is refused before it is stored."""
    text = _text("url", url, 2000)
    parts = urlsplit(text)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise InputError(f"url {text[:100]!r}: a webhook URL must be http:// or https:// with a host")
    return text


@dataclass(frozen=True)
class DueDelivery:
    delivery_id: int
    endpoint_id: int
    url: str
    secret: str
    attempts: int
    event: FeedEvent


class LimsStore(ActivationStore):
    # ------------------------------------------------------------ reference standards

    def add_standard(self, fields: Mapping[str, Any], *, actor: str) -> ReferenceStandard:
        sha = fields.get("certificate_sha256")
        if not isinstance(sha, str) or not _SHA256.fullmatch(sha):
            raise InputError("certificate_sha256 must be the 64 lower-case hex digits of the certificate file's SHA-256")
        calibrated, due = _date("calibrated_on", fields.get("calibrated_on")), _date("due_on", fields.get("due_on"))
        if due <= calibrated:
            raise InputError(f"due_on {due} must be after calibrated_on {calibrated}")
        model = fields.get("model")
        remark = fields.get("uncertainty")
        remark = _text("uncertainty", remark, 500) if remark not in (None, "") else ""
        U, k = _stated_uncertainty(fields, remark)
        row = ReferenceStandard(
            name=_text("name", fields.get("name")), serial=_text("serial", fields.get("serial")),
            model=_text("model", model) if model is not None else None,
            certificate_number=_text("certificate_number", fields.get("certificate_number")),
            certificate_sha256=sha, calibrated_on=calibrated, due_on=due,
            uncertainty=remark, expanded_uncertainty_deg=U, coverage_factor=k, created_at=utc_now(),
            created_by=_text("actor", actor),
        )  # fmt: skip
        with self._tx() as s:
            clash = s.scalar(sa.select(ReferenceStandard.id).where(
                ReferenceStandard.serial == row.serial, ReferenceStandard.certificate_number == row.certificate_number))
            if clash is not None:
                raise ConflictError(f"standard {clash} already holds certificate {row.certificate_number} of serial {row.serial}")
            s.add(row)
            s.flush()
            self._audit(s, actor, "standard.create", "reference_standard", row.id,
                        {"name": row.name, "serial": row.serial, "certificate_number": row.certificate_number,
                         "certificate_sha256": sha, "due_on": due.isoformat(),
                         "expanded_uncertainty_deg": U, "coverage_factor": k})  # fmt: skip
            return row

    def standards(self) -> list[ReferenceStandard]:
        with self._read() as s:
            return list(s.scalars(sa.select(ReferenceStandard).order_by(ReferenceStandard.id)))

    def standard(self, standard_id: int) -> ReferenceStandard:
        with self._read() as s:
            row = s.get(ReferenceStandard, standard_id)
            if row is None:
                raise UnknownEntity(f"reference standard {standard_id} does not exist")
            return row

    def usable_standards(self, ids: Sequence[object], *, on: dt.date) -> list[ReferenceStandard]:
        """The standards a job names, refused if one is unknown or past its due date on `on`."""
        if not isinstance(ids, list | tuple):
            raise StandardNotUsable("reference_standards", "must be a list of reference standard ids")
        out = []
        with self._read() as s:
            for i, sid in enumerate(ids):
                row = s.get(ReferenceStandard, sid) if isinstance(sid, int) and not isinstance(sid, bool) else None
                if row is None:
                    raise StandardNotUsable(f"reference_standards[{i}]", f"{sid!r} is not a registered reference standard")
                if row.due_on < on:
                    raise StandardNotUsable(
                        f"reference_standards[{i}]", f"standard {row.id} ({row.name}, serial {row.serial}, certificate "
                        f"{row.certificate_number}) was due for calibration on {row.due_on}; it cannot be used")
                if row.expanded_uncertainty_deg is None or row.coverage_factor is None:
                    raise StandardNotUsable(
                        f"reference_standards[{i}]", f"standard {row.id} ({row.name}, serial {row.serial}, certificate "
                        f"{row.certificate_number}) states no numeric uncertainty (its text {row.uncertainty!r} does not "
                        "read as an angle with its coverage factor); register it again with expanded_uncertainty_deg "
                        "and coverage_factor")
                out.append(row)
        return out

    def notify_standards_due(self, *, today: dt.date, within_days: int, actor: str = "daemon") -> list[int]:
        """A `standard.due_soon` event, once per due date, for each standard due within `within_days`."""
        with self._tx() as s:
            rows = list(s.scalars(sa.select(ReferenceStandard).where(
                ReferenceStandard.due_on <= today + dt.timedelta(days=within_days))))  # fmt: skip
            sent = []
            for row in rows:
                if row.due_soon_notified_on == row.due_on:
                    continue
                row.due_soon_notified_on = row.due_on
                self._audit(s, actor, "standard.due_soon", "reference_standard", row.id,
                            {"standard_id": row.id, "name": row.name, "serial": row.serial,
                             "certificate_number": row.certificate_number, "due_on": row.due_on.isoformat(),
                             "days_left": (row.due_on - today).days})  # fmt: skip
                sent.append(row.id)
            return sent

    # ------------------------------------------------------------ approvals

    def approvals(self, record_id: int) -> list[RecordApproval]:
        with self._read() as s:
            return list(s.scalars(sa.select(RecordApproval).where(RecordApproval.record_id == record_id)
                                  .order_by(RecordApproval.id)))

    @staticmethod
    def status_of(approvals: Sequence[RecordApproval]) -> str:
        if any(a.decision == "reject" for a in approvals):
            return "rejected"
        if any(a.decision == "approve" and a.meaning == "approval" for a in approvals):
            return "approved"
        return "draft"

    def record_status(self, record_id: int) -> str:
        return self.status_of(self.approvals(record_id))

    def record_statuses(self, record_ids: Sequence[int]) -> dict[int, str]:
        """The status of each of these records, in one query."""
        if not record_ids:
            return {}
        with self._read() as s:
            rows = list(s.scalars(sa.select(RecordApproval).where(RecordApproval.record_id.in_(list(record_ids)))))
        return {rid: self.status_of([a for a in rows if a.record_id == rid]) for rid in record_ids}

    def decide(self, record_id: int, *, decision: str, meaning: str, note: str, actor: str) -> RecordApproval:
        """Approve (meaning review or approval) or reject a draft record; never by who started or ran its job."""
        if decision not in ("approve", "reject"):
            raise InputError(f"decision {decision!r} is not approve or reject")
        if decision == "approve" and meaning not in APPROVE_MEANINGS:
            raise InputError(f"meaning {meaning!r}: an approval means one of {', '.join(APPROVE_MEANINGS)}")
        if decision == "reject":
            meaning = "rejection"
            _text("reason", note, 10_000)
        if not isinstance(note, str) or len(note) > 10_000:
            raise InputError("note must be text of at most 10,000 characters")
        actor = _text("actor", actor)
        with self._tx() as s:
            record = s.get(CalibrationRecord, record_id) if isinstance(record_id, int) else None
            if record is None:
                raise UnknownEntity(f"calibration record {record_id!r} does not exist")
            if sha256_hex(record_content(record)) != record.content_sha256:
                raise RefusedWrite(f"record {record_id} does not match its hash (tampered); it cannot be signed")
            job = s.get(CalibrationJob, record.job_id) if record.job_id is not None else None
            if actor == record.operator or (job is not None and actor == job.created_by):
                who = "started its job" if job is not None and actor == job.created_by else "ran it"
                raise SelfApproval(f"{actor!r} {who}; record {record_id} must be {decision}d by another person"
                                   " (segregation of duties)")
            past = list(s.scalars(sa.select(RecordApproval).where(RecordApproval.record_id == record_id)))
            status = self.status_of(past)
            if status != "draft":
                raise ConflictError(f"record {record_id} is already {status}; a decision is final")
            prev = s.execute(sa.select(RecordApproval.sha256).order_by(RecordApproval.id.desc()).limit(1)).scalar()
            row = RecordApproval(record_id=record_id, decision=decision, meaning=meaning, note=note, actor=actor,
                                 at=utc_now(), record_sha256=record.content_sha256, prev_sha256=prev or GENESIS_SHA256)
            row.sha256 = sha256_hex(normalise(approval_content(row)))
            s.add(row)
            s.flush()
            action = "record.reject" if decision == "reject" else ("record.approve" if meaning == "approval" else "record.review")
            self._audit(s, actor, action, "calibration_record", record_id,
                        {"approval_id": row.id, "actor": actor, "meaning": meaning, "note": note,
                         "record_sha256": record.content_sha256, "approval_sha256": row.sha256})  # fmt: skip
            active = s.get(ActiveCalibration, (record.device_id, record.kind))
            if decision == "reject" and active is not None and active.record_id == record_id:
                # a rejected record is never used: withdrawn in the same transaction as the rejection
                self._deactivate(s, record.device_id, record.kind, actor=actor, replaces=record_id,
                                 reason=f"record {record_id} v{record.version} was rejected: {note}")
            return row

    def verify_approvals(self) -> list[str]:
        """Problems of the approval chain: a row whose content or predecessor does not match (empty when sound)."""
        problems = []
        prev = GENESIS_SHA256
        with self._read() as s:
            for a in s.scalars(sa.select(RecordApproval).order_by(RecordApproval.id)):
                if sha256_hex(normalise(approval_content(a))) != a.sha256:
                    problems.append(f"approval {a.id}: content does not match its SHA-256")
                if a.prev_sha256 != prev:
                    problems.append(f"approval {a.id}: predecessor hash does not match approval before it")
                prev = a.sha256
        return problems

    # ------------------------------------------------------------ certificates

    def certificate_of(self, record_id: int) -> Certificate | None:
        with self._read() as s:
            return s.scalar(sa.select(Certificate).where(Certificate.record_id == record_id))

    def certificate_by_number(self, number: str) -> Certificate | None:
        with self._read() as s:
            return s.scalar(sa.select(Certificate).where(Certificate.number == number))

    def replaced_certificate(self, record_id: int) -> Certificate | None:
        """The newest certificate of an earlier version of the same device and kind (the one a new one replaces)."""
        with self._read() as s:
            r = s.get(CalibrationRecord, record_id)
            if r is None:
                return None
            return s.scalar(
                sa.select(Certificate).join(CalibrationRecord, CalibrationRecord.id == Certificate.record_id)
                .where(CalibrationRecord.device_id == r.device_id, CalibrationRecord.kind == r.kind,
                       CalibrationRecord.version < r.version)
                .order_by(CalibrationRecord.version.desc()).limit(1))  # fmt: skip

    def store_certificate(self, record_id: int, *, number: str, xml: bytes, approval_id: int,
                          replaces_id: int | None, actor: str) -> tuple[Certificate, bool]:
        """Keep issued bytes with their SHA-256; if the record already has a certificate, that one is returned."""
        with self._tx() as s:
            existing = s.scalar(sa.select(Certificate).where(Certificate.record_id == record_id))
            if existing is not None:
                return existing, False
            row = Certificate(record_id=record_id, number=_text("number", number), xml=bytes(xml),
                              sha256=hashlib.sha256(xml).hexdigest(), approval_id=approval_id, replaces_id=replaces_id,
                              issued_at=utc_now(), issued_by=_text("actor", actor))  # fmt: skip
            s.add(row)
            s.flush()
            replaced = s.get(Certificate, replaces_id) if replaces_id is not None else None
            self._audit(s, actor, "certificate.issue", "certificate", row.id,
                        {"certificate_id": row.id, "number": row.number, "record_id": record_id, "sha256": row.sha256,
                         "replaces": replaced.number if replaced else None})  # fmt: skip
            return row, True

    # ------------------------------------------------------------ orders

    def create_order(self, fields: Mapping[str, Any], *, actor: str,
                     idempotency_key: str | None = None) -> tuple[Order, bool]:
        """A new order, or (False) the one an earlier request with the same Idempotency-Key created."""
        body = normalise(dict(fields))
        request_sha = sha256_hex(body)
        customer = body.get("customer")
        if not isinstance(customer, Mapping):
            raise InputError("customer must be an object {name, city, country_code[, street, post_code, email]}")
        for key in ("name", "city"):
            _text(f"customer.{key}", customer.get(key), 200)
        if not isinstance(customer.get("country_code"), str) or not re.fullmatch(r"[A-Z]{2}", customer["country_code"]):
            raise InputError("customer.country_code must be two upper-case letters (ISO 3166-1)")
        due = body.get("due_on")
        with self._tx() as s:
            if idempotency_key is not None:
                key = _text("Idempotency-Key", idempotency_key, 200)
                seen = s.scalar(sa.select(Order).where(Order.idempotency_key == key))
                if seen is not None:
                    if seen.request_sha256 != request_sha:
                        raise IdempotencyKeyReused(f"Idempotency-Key {key!r} was used for another request body "
                                                   f"(order {seen.id}); use a new key for a new order")
                    return seen, False
            lims_id = _text("lims_order_id", body.get("lims_order_id"))
            clash = s.scalar(sa.select(Order.id).where(Order.lims_order_id == lims_id))
            if clash is not None:
                raise ConflictError(f"lims_order_id {lims_id!r} is already order {clash}")
            maker, model = body.get("item_manufacturer"), body.get("item_model")
            row = Order(lims_order_id=lims_id, item_serial=_text("item_serial", body.get("item_serial")),
                        item_manufacturer=_text("item_manufacturer", maker) if maker is not None else None,
                        item_model=_text("item_model", model) if model is not None else None,
                        customer=dict(customer), procedure=_text("procedure", body.get("procedure"), 40),
                        method=_text("method", body.get("method"), 80),
                        due_on=_date("due_on", due) if due is not None else None, created_at=utc_now(),
                        created_by=_text("actor", actor), idempotency_key=idempotency_key, request_sha256=request_sha)
            s.add(row)
            s.flush()
            self._audit(s, actor, "order.create", "order", row.id,
                        {"order_id": row.id, "lims_order_id": lims_id, "item_serial": row.item_serial})
            return row, True

    def order(self, order_id: int) -> Order:
        with self._read() as s:
            row = s.get(Order, order_id)
            if row is None:
                raise UnknownEntity(f"order {order_id} does not exist")
            return row

    def order_links(self, order_id: int) -> dict[str, Any]:
        """The order's jobs, records (with status) and certificates, and the state they put it in."""
        with self._read() as s:
            jobs = list(s.scalars(sa.select(CalibrationJob).where(CalibrationJob.order_id == order_id)
                                  .order_by(CalibrationJob.id)))
            job_ids = [j.id for j in jobs]
            records = list(s.scalars(sa.select(CalibrationRecord).where(CalibrationRecord.job_id.in_(job_ids))
                                     .order_by(CalibrationRecord.id))) if job_ids else []
            rec_ids = [r.id for r in records]
            approvals = list(s.scalars(sa.select(RecordApproval).where(RecordApproval.record_id.in_(rec_ids)))) if rec_ids else []
            certs = list(s.scalars(sa.select(Certificate).where(Certificate.record_id.in_(rec_ids))
                                   .order_by(Certificate.id))) if rec_ids else []
        status = {r.id: self.status_of([a for a in approvals if a.record_id == r.id]) for r in records}
        return {
            "jobs": [{"id": j.id, "state": j.state} for j in jobs],
            "records": [{"id": r.id, "version": r.version, "status": status[r.id]} for r in records],
            "certificates": [{"id": c.id, "number": c.number, "record_id": c.record_id, "sha256": c.sha256} for c in certs],
            "state": _order_state(jobs, records, status, certs),
        }

    # ------------------------------------------------------------ the feed

    def feed(self, *, after_id: int = 0, limit: int = 100, types: Sequence[str] | None = None) -> list[FeedEvent]:
        with self._read() as s:
            stmt = sa.select(FeedEvent).where(FeedEvent.id > after_id).order_by(FeedEvent.id).limit(limit)
            if types:
                stmt = stmt.where(FeedEvent.type.in_(list(types)))
            return list(s.scalars(stmt))

    # ------------------------------------------------------------ webhooks

    def add_webhook(self, url: object, events: object, *, actor: str) -> tuple[WebhookEndpoint, str]:
        """A webhook endpoint and its signing secret (returned here once; needed in clear to sign)."""
        url = webhook_url(url)
        if not isinstance(events, list) or not events or not all(isinstance(e, str) for e in events):
            raise InputError(f"events must be a non-empty list of event types ({', '.join(EVENT_TYPES)}) or ['*']")
        unknown = [e for e in events if e != "*" and e not in EVENT_TYPES]
        if unknown:
            raise InputError(f"events: {', '.join(unknown)} unknown; event types are {', '.join(EVENT_TYPES)} (or '*')")
        secret = "whsec_" + base64.b64encode(secrets.token_bytes(24)).decode()
        with self._tx() as s:
            row = WebhookEndpoint(url=url, events=sorted(set(events)), secret=secret, created_at=utc_now(),
                                  created_by=_text("actor", actor))
            s.add(row)
            s.flush()
            self._audit(s, actor, "webhook.create", "webhook_endpoint", row.id, {"url": url, "events": row.events})
            return row, secret

    def webhooks(self) -> list[WebhookEndpoint]:
        with self._read() as s:
            return list(s.scalars(sa.select(WebhookEndpoint).order_by(WebhookEndpoint.id)))

    def webhook(self, endpoint_id: int) -> WebhookEndpoint:
        with self._read() as s:
            row = s.get(WebhookEndpoint, endpoint_id)
            if row is None:
                raise UnknownEntity(f"webhook {endpoint_id} does not exist")
            return row

    def deliveries(self, endpoint_id: int, *, limit: int = 200) -> list[tuple[WebhookDelivery, FeedEvent, list[WebhookAttempt]]]:
        with self._read() as s:
            rows = s.execute(sa.select(WebhookDelivery, FeedEvent).join(FeedEvent, FeedEvent.id == WebhookDelivery.event_id)
                             .where(WebhookDelivery.endpoint_id == endpoint_id)
                             .order_by(WebhookDelivery.id.desc()).limit(limit)).all()  # fmt: skip
            ids = [d.id for d, _ in rows]
            attempts = list(s.scalars(sa.select(WebhookAttempt).where(WebhookAttempt.delivery_id.in_(ids))
                                      .order_by(WebhookAttempt.id))) if ids else []
        return [(d, e, [a for a in attempts if a.delivery_id == d.id]) for d, e in rows]

    def due_deliveries(self, *, now: dt.datetime, limit: int = 50) -> list[DueDelivery]:
        with self._read() as s:
            rows = s.execute(
                sa.select(WebhookDelivery, WebhookEndpoint, FeedEvent)
                .join(WebhookEndpoint, WebhookEndpoint.id == WebhookDelivery.endpoint_id)
                .join(FeedEvent, FeedEvent.id == WebhookDelivery.event_id)
                .where(WebhookDelivery.state == "pending", WebhookDelivery.next_attempt_at <= now,
                       WebhookEndpoint.disabled_at.is_(None))
                .order_by(WebhookDelivery.event_id, WebhookDelivery.id).limit(limit)
            ).all()  # fmt: skip
        return [DueDelivery(d.id, w.id, w.url, w.secret, d.attempts, e) for d, w, e in rows]

    def next_delivery_due(self) -> dt.datetime | None:
        with self._read() as s:
            return s.scalar(sa.select(sa.func.min(WebhookDelivery.next_attempt_at))
                            .where(WebhookDelivery.state == "pending"))

    def record_attempt(self, delivery_id: int, *, ok: bool, status_code: int | None, error: str | None,
                       duration_s: float, retry_at: dt.datetime | None) -> WebhookDelivery:
        """Log one attempt; delivered when ok, else pending until `retry_at` (None: given up, failed)."""
        now = utc_now()
        with self._tx() as s:
            d = s.get(WebhookDelivery, delivery_id)
            if d is None:
                raise UnknownEntity(f"delivery {delivery_id} does not exist")
            s.add(WebhookAttempt(delivery_id=delivery_id, at=now, status_code=status_code,
                                 error=(error or None) and error[:2000], duration_s=float(duration_s)))  # fmt: skip
            d.attempts += 1
            d.last_status_code, d.last_error = status_code, (error or None) and error[:2000]
            if ok:
                d.state, d.delivered_at, d.next_attempt_at = "delivered", now, None
            elif retry_at is None:
                d.state, d.next_attempt_at = "failed", None
            else:
                d.next_attempt_at = retry_at
            return d


def _order_state(jobs: list[CalibrationJob], records: list[CalibrationRecord], status: dict[int, str],
                 certs: list[Certificate]) -> str:
    """open -> in_progress -> measured -> approved -> certified; or failed / rejected for the latest attempt."""
    if not jobs:
        return "open"
    latest = records[-1] if records else None
    if latest is not None and any(c.record_id == latest.id for c in certs):
        return "certified"
    if latest is not None and status[latest.id] in ("approved", "rejected"):
        return status[latest.id]
    if any(j.state in ("queued", "running") for j in jobs):
        return "in_progress"
    if latest is not None:
        return "measured"
    return "failed" if jobs[-1].state in ("failed", "cancelled") else "in_progress"
