"""Orders from the LIMS: created once per Idempotency-Key, linked to their jobs, records and
certificates."""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from typing import TypedDict, TypeVar

import sqlalchemy as sa
from sqlalchemy.orm import Session

from service.errors import InputError
from service.storage.canonical import normalise, sha256_hex
from service.storage.errors import ConflictError
from service.storage.models import (
    CalibrationJob,
    CalibrationRecord,
    Certificate,
    JobState,
    Order,
    RecordApproval,
    utc_now,
)
from service.storage.specification import (
    Specification,
    SpecificationProblem,
    specification_of,
)
from service.storage.store.approvals import approval_status
from service.storage.store.checks import require_date, require_text
from service.storage.store.database import Database
from service.storage.store.lookups import row_in

_Row = TypeVar("_Row", CalibrationRecord, RecordApproval, Certificate)


class IdempotencyKeyReused(InputError):
    """The same Idempotency-Key came with another body."""


class JobLink(TypedDict):
    id: int
    state: str


class RecordLink(TypedDict):
    id: int
    version: int
    status: str  # draft, approved or rejected


class CertificateLink(TypedDict):
    id: int
    number: str
    record_id: int
    sha256: str


class OrderLinks(TypedDict):
    """An order's jobs, records (with their approval status) and certificates, and the state they
    put it in."""

    jobs: list[JobLink]
    records: list[RecordLink]
    certificates: list[CertificateLink]
    state: str


def _customer_of(body: Mapping[str, object]) -> Mapping[str, str]:
    """The order's customer, checked: a name, a city and an ISO 3166-1 country code at least (its
    values text, as the API's order model gives them)."""
    customer = body.get("customer")
    if not isinstance(customer, Mapping):
        raise InputError(
            "customer must be an object {name, city, country_code[, street, post_code, email]}"
        )
    for key in ("name", "city"):
        require_text(f"customer.{key}", customer.get(key), 200)
    if not isinstance(customer.get("country_code"), str) or not re.fullmatch(
        r"[A-Z]{2}", customer["country_code"]
    ):
        raise InputError("customer.country_code must be two upper-case letters (ISO 3166-1)")
    return customer


def _specification_of_order(body: Mapping[str, object]) -> Specification | None:
    """The order's specification, if any: conformity is stated on a stage-grid order's indication
    error only."""
    spec = specification_of(body.get("specification"))
    if spec is not None and body.get("procedure") != "stage-grid":
        raise SpecificationProblem(
            "specification",
            "statements of conformity are made on the indication error of a "
            f"biaxial inclinometer: a stage-grid order, not {body.get('procedure')!r}",
        )
    return spec


def _order_of_key(session: Session, idempotency_key: str, request_sha: str) -> Order | None:
    """The order an earlier request with this Idempotency-Key created (None: a new key); the key
    may not come back with another body."""
    key = require_text("Idempotency-Key", idempotency_key, 200)
    seen = session.scalar(sa.select(Order).where(Order.idempotency_key == key))
    if seen is not None and seen.request_sha256 != request_sha:
        raise IdempotencyKeyReused(
            f"Idempotency-Key {key!r} was used for another request body "
            f"(order {seen.id}); use a new key for a new order"
        )
    return seen


def _rows_with_ids_in(
    session: Session,
    entity: type[_Row],
    column: sa.orm.InstrumentedAttribute[int | None],
    ids: list[int],
    *order_by: sa.orm.InstrumentedAttribute[int],
) -> list[_Row]:
    """The rows whose `column` is one of `ids` (none asked for: no query), in order."""
    if not ids:
        return []
    stmt = sa.select(entity).where(column.in_(ids))
    if order_by:
        stmt = stmt.order_by(*order_by)
    return list(session.scalars(stmt))


class OrdersRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def create_order(
        self, fields: Mapping[str, object], *, actor: str, idempotency_key: str | None = None
    ) -> tuple[Order, bool]:
        """A new order, or (False) the one an earlier request with the same Idempotency-Key
        created."""
        body = normalise(dict(fields))
        request_sha = sha256_hex(body)
        customer = _customer_of(body)
        due = body.get("due_on")
        spec = _specification_of_order(body)
        with self._db.transaction() as session:
            if idempotency_key is not None:
                seen = _order_of_key(session, idempotency_key, request_sha)
                if seen is not None:
                    return seen, False
            lims_id = require_text("lims_order_id", body.get("lims_order_id"))
            clash = session.scalar(sa.select(Order.id).where(Order.lims_order_id == lims_id))
            if clash is not None:
                raise ConflictError(f"lims_order_id {lims_id!r} is already order {clash}")
            maker, model = body.get("item_manufacturer"), body.get("item_model")
            row = Order(
                lims_order_id=lims_id,
                item_serial=require_text("item_serial", body.get("item_serial")),
                item_manufacturer=require_text("item_manufacturer", maker)
                if maker is not None
                else None,
                item_model=require_text("item_model", model) if model is not None else None,
                customer=dict(customer),
                procedure=require_text("procedure", body.get("procedure"), 40),
                method=require_text("method", body.get("method"), 80),
                due_on=require_date("due_on", due) if due is not None else None,
                created_at=utc_now(),
                created_by=require_text("actor", actor),
                idempotency_key=idempotency_key,
                request_sha256=request_sha,
                specification=spec.as_json() if spec is not None else None,
            )
            session.add(row)
            session.flush()
            self._db.audit(
                session,
                actor,
                "order.create",
                "order",
                row.id,
                {
                    "order_id": row.id,
                    "lims_order_id": lims_id,
                    "item_serial": row.item_serial,
                    "specification": row.specification,
                },
            )
            return row, True

    def get(self, order_id: int) -> Order:
        with self._db.session() as session:
            return row_in(session, Order, order_id, "order")

    def specified_jobs(self, job_ids: Sequence[int]) -> set[int]:
        """Which of these jobs work on an order with a specification (their records state
        conformity), in one query."""
        if not job_ids:
            return set()
        with self._db.session() as session:
            rows = session.execute(
                sa.select(CalibrationJob.id, Order.specification)
                .join(Order, Order.id == CalibrationJob.order_id)
                .where(CalibrationJob.id.in_(list(job_ids)))
            )
            # a JSON column keeps "no specification" as null
            return {int(job_id) for job_id, spec in rows if spec}

    def order_links(self, order_id: int) -> OrderLinks:
        """The order's jobs, records (with status) and certificates, and the state they put it
        in."""
        with self._db.session() as session:
            jobs = list(
                session.scalars(
                    sa.select(CalibrationJob)
                    .where(CalibrationJob.order_id == order_id)
                    .order_by(CalibrationJob.id)
                )
            )
            job_ids = [job.id for job in jobs]
            records = _rows_with_ids_in(
                session, CalibrationRecord, CalibrationRecord.job_id, job_ids, CalibrationRecord.id
            )
            rec_ids = [record.id for record in records]
            approvals = _rows_with_ids_in(
                session, RecordApproval, RecordApproval.record_id, rec_ids
            )
            certs = _rows_with_ids_in(
                session, Certificate, Certificate.record_id, rec_ids, Certificate.id
            )
        status = {
            record.id: approval_status(
                [approval for approval in approvals if approval.record_id == record.id]
            )
            for record in records
        }
        return {
            "jobs": [{"id": job.id, "state": job.state} for job in jobs],
            "records": [
                {"id": record.id, "version": record.version, "status": status[record.id]}
                for record in records
            ],
            "certificates": [
                {
                    "id": cert.id,
                    "number": cert.number,
                    "record_id": cert.record_id,
                    "sha256": cert.sha256,
                }
                for cert in certs
            ],
            "state": order_state(jobs, records, status, certs),
        }


def order_state(
    jobs: list[CalibrationJob],
    records: list[CalibrationRecord],
    status: dict[int, str],
    certs: list[Certificate],
) -> str:
    """open -> in_progress -> measured -> approved -> certified; or failed / rejected for the latest
    attempt."""
    if not jobs:
        return "open"
    latest = records[-1] if records else None
    decided = _decided_state(latest, status, certs)
    if decided is not None:
        return decided
    if any(job.state in (JobState.QUEUED, JobState.RUNNING) for job in jobs):
        return "in_progress"
    if latest is not None:
        return "measured"
    return "failed" if jobs[-1].state in ("failed", "cancelled") else "in_progress"


def _decided_state(
    latest: CalibrationRecord | None, status: dict[int, str], certs: list[Certificate]
) -> str | None:
    """The state the latest record's decision puts an order in (certified, approved, rejected),
    or None while it has none."""
    if latest is not None and any(cert.record_id == latest.id for cert in certs):
        return "certified"
    if latest is not None and status[latest.id] in ("approved", "rejected"):
        return status[latest.id]
    return None
