"""The active pointer: at most one active calibration per (device, kind); every switch deliberate
and audited.

These run inside a caller's transaction: the records' own writes, and a rejection that withdraws its
record.
"""

from __future__ import annotations

import sqlalchemy as sa
from sqlalchemy.orm import Session

from service.storage.canonical import sha256_hex
from service.storage.errors import ConflictError, RecordNotUsable
from service.storage.models import (
    ActiveCalibration,
    ActiveCalibrationHistory,
    CalibrationRecord,
    RecordApproval,
    utc_now,
)
from service.storage.store.checks import require_text
from service.storage.store.database import Database
from service.storage.store.hashing import record_content


def activate_in(
    db: Database,
    session: Session,
    record: CalibrationRecord,
    *,
    actor: str,
    reason: str,
    replaces: int | None,
) -> ActiveCalibration:
    """Make `record` the active version inside the caller's transaction (see
    RecordsRepo.activate)."""
    actor, reason = require_text("actor", actor), require_text("reason", reason, 10_000)
    why = unusable_in(session, record)
    if why is not None:
        raise RecordNotUsable(f"{why}; it cannot be activated")
    current = session.get(ActiveCalibration, (record.device_id, record.kind))
    current_id = current.record_id if current else None
    if current_id != replaces:
        if current is None:
            raise ConflictError(
                f"device {record.device_id} has no active {record.kind} calibration, not record "
                f"{replaces}"
            )
        raise ConflictError(
            f"device {record.device_id} already has an active {record.kind} calibration (record "
            f"{current_id}); a second active pointer is refused: pass replaces={current_id} to "
            f"switch to record {record.id}"
        )
    now = utc_now()
    if current is None:
        current = ActiveCalibration(
            device_id=record.device_id,
            kind=record.kind,
            record_id=record.id,
            set_at=now,
            set_by=actor,
            reason=reason,
        )
        session.add(current)
    else:
        current.record_id, current.set_at, current.set_by, current.reason = (
            record.id,
            now,
            actor,
            reason,
        )
    session.add(
        ActiveCalibrationHistory(
            device_id=record.device_id,
            kind=record.kind,
            record_id=record.id,
            previous_record_id=current_id,
            changed_at=now,
            changed_by=actor,
            reason=reason,
        )
    )
    db.audit(
        session,
        actor,
        "pointer.set",
        "active_calibration",
        f"{record.device_id}/{record.kind}",
        {
            "record_id": record.id,
            "version": record.version,
            "previous_record_id": current_id,
            "content_sha256": record.content_sha256,
            "reason": reason,
        },
    )
    return current


def unusable_in(session: Session, record: CalibrationRecord) -> str | None:
    """Why the record must not correct anything (rejected, or not matching its hash), or None if it
    may."""
    if sha256_hex(record_content(record)) != record.content_sha256:
        return (
            f"record {record.id} v{record.version}: its stored content does not match its SHA-256"
            " (tampered: changed after it was made)"
        )
    rejection = session.scalar(
        sa.select(RecordApproval)
        .where(RecordApproval.record_id == record.id, RecordApproval.decision == "reject")
        .limit(1)
    )
    if rejection is not None:
        return (
            f"record {record.id} v{record.version} was rejected by {rejection.actor}: "
            f"{rejection.note}"
        )
    return None


def deactivate_in(
    db: Database,
    session: Session,
    device_id: int,
    kind: str,
    *,
    actor: str,
    reason: str,
    replaces: int,
) -> None:
    """Withdraw the active version inside the caller's transaction (see RecordsRepo.deactivate)."""
    actor, reason = require_text("actor", actor), require_text("reason", reason, 10_000)
    current = session.get(ActiveCalibration, (device_id, kind))
    if current is None or current.record_id != replaces:
        raise ConflictError(
            f"device {device_id} {kind}: active record is "
            f"{current.record_id if current else None}, not {replaces}"
        )
    session.delete(current)
    session.add(
        ActiveCalibrationHistory(
            device_id=device_id,
            kind=kind,
            record_id=None,
            previous_record_id=replaces,
            changed_at=utc_now(),
            changed_by=actor,
            reason=reason,
        )
    )
    db.audit(
        session,
        actor,
        "pointer.clear",
        "active_calibration",
        f"{device_id}/{kind}",
        {"record_id": None, "previous_record_id": replaces, "reason": reason},
    )
