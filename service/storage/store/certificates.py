"""Issued certificates: the bytes as issued with their SHA-256, one per record, naming the one they
replace."""

from __future__ import annotations

import hashlib
from collections.abc import Mapping

import sqlalchemy as sa

from service.storage.models import CalibrationRecord, Certificate, utc_now
from service.storage.store.checks import require_text
from service.storage.store.database import Database


class CertificatesRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def certificate_of(self, record_id: int) -> Certificate | None:
        with self._db.session() as session:
            return session.scalar(sa.select(Certificate).where(Certificate.record_id == record_id))

    def certificate_by_number(self, number: str) -> Certificate | None:
        with self._db.session() as session:
            return session.scalar(sa.select(Certificate).where(Certificate.number == number))

    def replaced_certificate(self, record_id: int) -> Certificate | None:
        """The newest certificate of an earlier version of the same device and kind (the one a new
        one replaces)."""
        with self._db.session() as session:
            record = session.get(CalibrationRecord, record_id)
            if record is None:
                return None
            return session.scalar(
                sa.select(Certificate)
                .join(CalibrationRecord, CalibrationRecord.id == Certificate.record_id)
                .where(
                    CalibrationRecord.device_id == record.device_id,
                    CalibrationRecord.kind == record.kind,
                    CalibrationRecord.version < record.version,
                )
                .order_by(CalibrationRecord.version.desc())
                .limit(1)
            )

    def store_certificate(
        self,
        record_id: int,
        *,
        number: str,
        xml: bytes,
        approval_id: int,
        replaces_id: int | None,
        actor: str,
        conformity: Mapping[str, object] | None = None,
    ) -> tuple[Certificate, bool]:
        """Keep issued bytes with their SHA-256; if the record already has a certificate, that one
        is returned. `conformity`: the statements of conformity it makes, which its
        `certificate.issued` event carries."""
        with self._db.transaction() as session:
            existing = session.scalar(
                sa.select(Certificate).where(Certificate.record_id == record_id)
            )
            if existing is not None:
                return existing, False
            row = Certificate(
                record_id=record_id,
                number=require_text("number", number),
                xml=bytes(xml),
                sha256=hashlib.sha256(xml).hexdigest(),
                approval_id=approval_id,
                replaces_id=replaces_id,
                issued_at=utc_now(),
                issued_by=require_text("actor", actor),
            )
            session.add(row)
            session.flush()
            replaced = session.get(Certificate, replaces_id) if replaces_id is not None else None
            self._db.audit(
                session,
                actor,
                "certificate.issue",
                "certificate",
                row.id,
                {
                    "certificate_id": row.id,
                    "number": row.number,
                    "record_id": record_id,
                    "sha256": row.sha256,
                    "replaces": replaced.number if replaced else None,
                    "conformity": dict(conformity) if conformity is not None else None,
                },
            )
            return row, True
