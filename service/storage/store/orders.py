"""Orders from the LIMS: created once per Idempotency-Key, linked to their jobs, records and
certificates."""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from typing import Any

import sqlalchemy as sa

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
from service.storage.specification import SpecificationProblem, specification_of
from service.storage.store.approvals import approval_status
from service.storage.store.checks import require_date, require_text
from service.storage.store.database import Database
from service.storage.store.lookups import row_in


class IdempotencyKeyReused(InputError):
    """The same Idempotency-Key came with another body."""


class OrdersRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def create_order(
        self, fields: Mapping[str, Any], *, actor: str, idempotency_key: str | None = None
    ) -> tuple[Order, bool]:
        """A new order, or (False) the one an earlier request with the same Idempotency-Key
        created."""
        body = normalise(dict(fields))
        request_sha = sha256_hex(body)
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
        due = body.get("due_on")
        spec = specification_of(body.get("specification"))
        if spec is not None and body.get("procedure") != "stage-grid":
            raise SpecificationProblem(
                "specification",
                "statements of conformity are made on the indication error of a "
                f"biaxial inclinometer: a stage-grid order, not {body.get('procedure')!r}",
            )
        with self._db.transaction() as session:
            if idempotency_key is not None:
                key = require_text("Idempotency-Key", idempotency_key, 200)
                seen = session.scalar(sa.select(Order).where(Order.idempotency_key == key))
                if seen is not None:
                    if seen.request_sha256 != request_sha:
                        raise IdempotencyKeyReused(
                            f"Idempotency-Key {key!r} was used for another request body "
                            f"(order {seen.id}); use a new key for a new order"
                        )
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
        with self._db.session() as s:
            return row_in(s, Order, order_id, "order")

    def specified_jobs(self, job_ids: Sequence[int]) -> set[int]:
        """Which of these jobs work on an order with a specification (their records state
        conformity), in one query."""
        if not job_ids:
            return set()
        with self._db.session() as s:
            rows = s.execute(
                sa.select(CalibrationJob.id, Order.specification)
                .join(Order, Order.id == CalibrationJob.order_id)
                .where(CalibrationJob.id.in_(list(job_ids)))
            )
            # a JSON column keeps "no specification" as null
            return {int(job_id) for job_id, spec in rows if spec}

    def order_links(self, order_id: int) -> dict[str, Any]:
        """The order's jobs, records (with status) and certificates, and the state they put it
        in."""
        with self._db.session() as s:
            jobs = list(
                s.scalars(
                    sa.select(CalibrationJob)
                    .where(CalibrationJob.order_id == order_id)
                    .order_by(CalibrationJob.id)
                )
            )
            job_ids = [j.id for j in jobs]
            records = (
                list(
                    s.scalars(
                        sa.select(CalibrationRecord)
                        .where(CalibrationRecord.job_id.in_(job_ids))
                        .order_by(CalibrationRecord.id)
                    )
                )
                if job_ids
                else []
            )
            rec_ids = [record.id for record in records]
            approvals = (
                list(
                    s.scalars(
                        sa.select(RecordApproval).where(RecordApproval.record_id.in_(rec_ids))
                    )
                )
                if rec_ids
                else []
            )
            certs = (
                list(
                    s.scalars(
                        sa.select(Certificate)
                        .where(Certificate.record_id.in_(rec_ids))
                        .order_by(Certificate.id)
                    )
                )
                if rec_ids
                else []
            )
        status = {
            record.id: approval_status(
                [approval for approval in approvals if approval.record_id == record.id]
            )
            for record in records
        }
        return {
            "jobs": [{"id": j.id, "state": j.state} for j in jobs],
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
    if latest is not None and any(cert.record_id == latest.id for cert in certs):
        return "certified"
    if latest is not None and status[latest.id] in ("approved", "rejected"):
        return status[latest.id]
    if any(j.state in (JobState.QUEUED, JobState.RUNNING) for j in jobs):
        return "in_progress"
    if latest is not None:
        return "measured"
    return "failed" if jobs[-1].state in ("failed", "cancelled") else "in_progress"
