"""Approvals of records: review, approval or rejection, never by who started or ran the job; the
approvals form their own hash chain, and a rejection withdraws its record from use at once."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NotRequired, TypedDict

import sqlalchemy as sa
from sqlalchemy.orm import Session

from service.errors import InputError
from service.storage.canonical import normalise, sha256_hex, utc_iso
from service.storage.errors import ConflictError, RefusedWrite
from service.storage.models import (
    GENESIS_SHA256,
    ActiveCalibration,
    CalibrationJob,
    CalibrationRecord,
    RecordApproval,
    utc_now,
)
from service.storage.store.checks import require_text
from service.storage.store.database import Database
from service.storage.store.hashing import record_content
from service.storage.store.lookups import row_in
from service.storage.store.pointer import deactivate_in
from service.storage.tokens import NamedPerson, Person

APPROVE_MEANINGS = ("review", "approval")


class SelfApproval(RefusedWrite):
    """Segregation of duties: the one who started the job (or ran it) may not approve or reject its
    record."""


class ApprovalContent(TypedDict):
    """What an approval asserts, hashed into its `sha256`; the signer where the approval names
    one."""

    record_id: int
    decision: str
    meaning: str
    note: str
    actor: str
    at: str
    record_sha256: str
    prev_sha256: str
    signer: NotRequired[NamedPerson]


def approval_content(a: RecordApproval) -> ApprovalContent:
    """What an approval asserts; its SHA-256 is `sha256` (canonical rule of canonical.py). The
    signer's name and function are part of it where the approval names them (approvals from before
    persons were kept do not)."""
    content: ApprovalContent = {
        "record_id": a.record_id,
        "decision": a.decision,
        "meaning": a.meaning,
        "note": a.note,
        "actor": a.actor,
        "at": utc_iso(a.at),
        "record_sha256": a.record_sha256,
        "prev_sha256": a.prev_sha256,
    }
    if a.signer_name is not None:
        content["signer"] = {"name": a.signer_name, "function": a.signer_function}
    return content


def signer_of(a: RecordApproval) -> Person | None:
    """The person who signed an approval, as they were named when they signed."""
    return Person(a.signer_name, a.signer_function) if a.signer_name else None


def approval_status(approvals: Sequence[RecordApproval]) -> str:
    """draft, approved (an approval meaning approval) or rejected (any rejection)."""
    if any(approval.decision == "reject" for approval in approvals):
        return "rejected"
    if any(
        approval.decision == "approve" and approval.meaning == "approval" for approval in approvals
    ):
        return "approved"
    return "draft"


def _checked_meaning(decision: str, meaning: str, note: str) -> str:
    """What a decision means, checked with its note before anything is read: a rejection means
    rejection and gives its reason."""
    if decision not in ("approve", "reject"):
        raise InputError(f"decision {decision!r} is not approve or reject")
    if decision == "approve" and meaning not in APPROVE_MEANINGS:
        raise InputError(
            f"meaning {meaning!r}: an approval means one of {', '.join(APPROVE_MEANINGS)}"
        )
    if decision == "reject":
        meaning = "rejection"
        require_text("reason", note, 10_000)
    if not isinstance(note, str) or len(note) > 10_000:
        raise InputError("note must be text of at most 10,000 characters")
    return meaning


def _signable_record(
    session: Session, record_id: int, decision: str, actor: str
) -> CalibrationRecord:
    """The record to decide on: untampered, and neither started nor run by the one deciding."""
    record = row_in(session, CalibrationRecord, record_id, "calibration record")
    if sha256_hex(record_content(record)) != record.content_sha256:
        raise RefusedWrite(
            f"record {record_id} does not match its hash (tampered); it cannot be signed"
        )
    job = session.get(CalibrationJob, record.job_id) if record.job_id is not None else None
    if actor == record.operator or (job is not None and actor == job.created_by):
        who = "started its job" if job is not None and actor == job.created_by else "ran it"
        raise SelfApproval(
            f"{actor!r} {who}; record {record_id} must be {decision}d by another person"
            " (segregation of duties)"
        )
    return record


class ApprovalsRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def of_record(self, record_id: int) -> list[RecordApproval]:
        with self._db.session() as session:
            return list(
                session.scalars(
                    sa.select(RecordApproval)
                    .where(RecordApproval.record_id == record_id)
                    .order_by(RecordApproval.id)
                )
            )

    @staticmethod
    def status_of(approvals: Sequence[RecordApproval]) -> str:
        return approval_status(approvals)

    def record_status(self, record_id: int) -> str:
        return approval_status(self.of_record(record_id))

    def record_statuses(self, record_ids: Sequence[int]) -> dict[int, str]:
        """The status of each of these records, in one query."""
        if not record_ids:
            return {}
        with self._db.session() as session:
            rows = list(
                session.scalars(
                    sa.select(RecordApproval).where(RecordApproval.record_id.in_(list(record_ids)))
                )
            )
        return {
            rid: approval_status([approval for approval in rows if approval.record_id == rid])
            for rid in record_ids
        }

    def decide(
        self,
        record_id: int,
        *,
        decision: str,
        meaning: str,
        note: str,
        actor: str,
        signer: Person | None = None,
    ) -> RecordApproval:
        """Approve (meaning review or approval) or reject a draft record; never by who started or
        ran its job. `signer` is the person behind the actor's token, kept with the decision (a
        certificate names them)."""
        meaning = _checked_meaning(decision, meaning, note)
        actor = require_text("actor", actor)
        with self._db.transaction() as session:
            record = _signable_record(session, record_id, decision, actor)
            past = list(
                session.scalars(
                    sa.select(RecordApproval).where(RecordApproval.record_id == record_id)
                )
            )
            status = approval_status(past)
            if status != "draft":
                raise ConflictError(f"record {record_id} is already {status}; a decision is final")
            prev = session.execute(
                sa.select(RecordApproval.sha256).order_by(RecordApproval.id.desc()).limit(1)
            ).scalar()
            row = RecordApproval(
                record_id=record_id,
                decision=decision,
                meaning=meaning,
                note=note,
                actor=actor,
                at=utc_now(),
                record_sha256=record.content_sha256,
                prev_sha256=prev or GENESIS_SHA256,
                signer_name=signer.name if signer else None,
                signer_function=signer.function if signer else None,
            )
            row.sha256 = sha256_hex(normalise(approval_content(row)))
            session.add(row)
            session.flush()
            action = (
                "record.reject"
                if decision == "reject"
                else ("record.approve" if meaning == "approval" else "record.review")
            )
            self._db.audit(
                session,
                actor,
                action,
                "calibration_record",
                record_id,
                {
                    "approval_id": row.id,
                    "actor": actor,
                    "meaning": meaning,
                    "note": note,
                    "record_sha256": record.content_sha256,
                    "approval_sha256": row.sha256,
                    "signer": {"name": signer.name, "function": signer.function}
                    if signer
                    else None,
                },
            )
            self._withdraw_if_rejected(session, record, decision, note, actor)
            return row

    def _withdraw_if_rejected(
        self, session: Session, record: CalibrationRecord, decision: str, note: str, actor: str
    ) -> None:
        """A rejected record is never used: withdrawn (if active) in the rejection's own
        transaction."""
        active = session.get(ActiveCalibration, (record.device_id, record.kind))
        if decision == "reject" and active is not None and active.record_id == record.id:
            deactivate_in(
                self._db,
                session,
                record.device_id,
                record.kind,
                actor=actor,
                replaces=record.id,
                reason=f"record {record.id} v{record.version} was rejected: {note}",
            )

    def verify_approvals(self) -> list[str]:
        """Problems of the approval chain: a row whose content or predecessor does not match (empty
        when sound)."""
        problems: list[str] = []
        prev = GENESIS_SHA256
        with self._db.session() as session:
            for approval in session.scalars(sa.select(RecordApproval).order_by(RecordApproval.id)):
                if sha256_hex(normalise(approval_content(approval))) != approval.sha256:
                    problems.append(f"approval {approval.id}: content does not match its SHA-256")
                if approval.prev_sha256 != prev:
                    problems.append(
                        f"approval {approval.id}: predecessor "
                        "hash does not match approval before it"
                    )
                prev = approval.sha256
        return problems
