"""The active pointer: at most one active calibration per (device, kind); every switch deliberate and audited."""

from __future__ import annotations

import sqlalchemy as sa
from sqlalchemy.orm import Session

from service.storage.canonical import sha256_hex
from service.storage.errors import ConflictError, RecordNotUsable, UnknownEntity
from service.storage.models import (
    ActiveCalibration,
    ActiveCalibrationHistory,
    CalibrationRecord,
    RecordApproval,
    utc_now,
)
from service.storage.store.base import StoreBase
from service.storage.store.checks import _text
from service.storage.store.hashing import record_content


class ActivationStore(StoreBase):
    def activate(self, record_id: int, *, actor: str, reason: str, replaces: int | None = None) -> ActiveCalibration:
        """Make a record the active version of its (device, kind).

        `replaces` names the record the caller believes is active now (None: none is). If another
        one is active the change is refused: there is never a second active pointer, and a switch
        is always a deliberate, audited act.
        """
        with self._tx() as s:
            record = s.get(CalibrationRecord, record_id) if isinstance(record_id, int) else None
            if record is None:
                raise UnknownEntity(f"calibration record {record_id!r} does not exist")
            return self._activate(s, record, actor=actor, reason=reason, replaces=replaces)

    def _activate(
        self, s: Session, record: CalibrationRecord, *, actor: str, reason: str, replaces: int | None
    ) -> ActiveCalibration:
        actor, reason = _text("actor", actor), _text("reason", reason, 10_000)
        why = self._unusable(s, record)
        if why is not None:
            raise RecordNotUsable(f"{why}; it cannot be activated")
        current = s.get(ActiveCalibration, (record.device_id, record.kind))
        current_id = current.record_id if current else None
        if current_id != replaces:
            if current is None:
                raise ConflictError(
                    f"device {record.device_id} has no active {record.kind} calibration, not record {replaces}"
                )
            raise ConflictError(
                f"device {record.device_id} already has an active {record.kind} calibration (record {current_id});"
                f" a second active pointer is refused: pass replaces={current_id} to switch to record {record.id}"
            )
        now = utc_now()
        if current is None:
            current = ActiveCalibration(
                device_id=record.device_id, kind=record.kind, record_id=record.id, set_at=now, set_by=actor, reason=reason
            )
            s.add(current)
        else:
            current.record_id, current.set_at, current.set_by, current.reason = record.id, now, actor, reason
        s.add(ActiveCalibrationHistory(
            device_id=record.device_id, kind=record.kind, record_id=record.id, previous_record_id=current_id,
            changed_at=now, changed_by=actor, reason=reason,
        ))  # fmt: skip
        self._audit(
            s, actor, "pointer.set", "active_calibration", f"{record.device_id}/{record.kind}",
            {"record_id": record.id, "version": record.version, "previous_record_id": current_id,
             "content_sha256": record.content_sha256, "reason": reason},
        )  # fmt: skip
        return current

    def unusable_reason(self, record_id: int) -> str | None:
        """Why the record must not correct anything (rejected, or not matching its hash), or None if it may."""
        with self._read() as s:
            record = s.get(CalibrationRecord, record_id)
            if record is None:
                raise UnknownEntity(f"calibration record {record_id!r} does not exist")
            return self._unusable(s, record)

    @staticmethod
    def _unusable(s: Session, record: CalibrationRecord) -> str | None:
        if sha256_hex(record_content(record)) != record.content_sha256:
            return (f"record {record.id} v{record.version}: its stored content does not match its SHA-256"
                    " (tampered: changed after it was made)")
        rejection = s.scalar(sa.select(RecordApproval).where(
            RecordApproval.record_id == record.id, RecordApproval.decision == "reject").limit(1))  # fmt: skip
        if rejection is not None:
            return f"record {record.id} v{record.version} was rejected by {rejection.actor}: {rejection.note}"
        return None

    def inactive_reason(self, device_id: int, kind: str) -> str | None:
        """Why (device, kind) has no active record, when its pointer was withdrawn: the reason of that change."""
        with self._read() as s:
            last = s.scalar(sa.select(ActiveCalibrationHistory)
                            .where(ActiveCalibrationHistory.device_id == device_id, ActiveCalibrationHistory.kind == kind)
                            .order_by(ActiveCalibrationHistory.id.desc()).limit(1))  # fmt: skip
        if last is None or last.record_id is not None:
            return None
        return f"record {last.previous_record_id} was deactivated by {last.changed_by}: {last.reason}"

    def deactivate(self, device_id: int, kind: str, *, actor: str, reason: str, replaces: int) -> None:
        """Withdraw the active version (e.g. the device failed validation); audited like a switch."""
        with self._tx() as s:
            self._deactivate(s, device_id, kind, actor=actor, reason=reason, replaces=replaces)

    def _deactivate(self, s: Session, device_id: int, kind: str, *, actor: str, reason: str, replaces: int) -> None:
        actor, reason = _text("actor", actor), _text("reason", reason, 10_000)
        current = s.get(ActiveCalibration, (device_id, kind))
        if current is None or current.record_id != replaces:
            raise ConflictError(
                f"device {device_id} {kind}: active record is {current.record_id if current else None}, not {replaces}"
            )
        s.delete(current)
        s.add(ActiveCalibrationHistory(
            device_id=device_id, kind=kind, record_id=None, previous_record_id=replaces,
            changed_at=utc_now(), changed_by=actor, reason=reason,
        ))  # fmt: skip
        self._audit(s, actor, "pointer.clear", "active_calibration", f"{device_id}/{kind}",
                    {"record_id": None, "previous_record_id": replaces, "reason": reason})  # fmt: skip
