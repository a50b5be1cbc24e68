"""The store's sessions: reads, serialised write transactions, the audit chain and the entity lookups.

Write transactions are serialised (SQLite: BEGIN IMMEDIATE; PostgreSQL: a transaction advisory
lock), which keeps the audit chain and the version numbers linear; the unique constraints on the
chains are the backstop if anything bypasses this.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager

import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from service.storage.canonical import normalise, sha256_hex
from service.storage.engine import write_engine
from service.storage.errors import UnknownEntity
from service.storage.feed import append_for_audit
from service.storage.models import GENESIS_SHA256, AuditEvent, CalibrationJob, Device, utc_now
from service.storage.store.checks import _text, _translate
from service.storage.store.hashing import audit_content

_PG_WRITE_LOCK = 0x7417_1AB1


class StoreBase:
    def __init__(self, engine: sa.Engine) -> None:
        self.engine = engine
        self._read = sessionmaker(bind=engine, expire_on_commit=False)
        self._write = sessionmaker(bind=write_engine(engine), expire_on_commit=False)

    @contextmanager
    def session(self) -> Iterator[Session]:
        """A read session (or for callers composing their own work; flushes still pass the append-only guard)."""
        with self._read() as s:
            yield s

    @contextmanager
    def _tx(self) -> Iterator[Session]:
        with self._write() as s:
            try:
                with s.begin():
                    if s.bind.dialect.name == "postgresql":  # type: ignore[union-attr]
                        s.execute(sa.text("SELECT pg_advisory_xact_lock(:k)"), {"k": _PG_WRITE_LOCK})
                    yield s
            except (sa.exc.IntegrityError, sa.exc.DataError) as exc:  # the guard triggers' refusals included
                raise _translate(exc) from exc

    # ------------------------------------------------------------ audit

    def _audit(self, s: Session, actor: str, action: str, entity: str, entity_id: object, details: Mapping) -> AuditEvent:
        s.flush()  # the action's rows first, so their ids are known and constraints have run
        prev = s.execute(sa.select(AuditEvent.sha256).order_by(AuditEvent.id.desc()).limit(1)).scalar()
        event = AuditEvent(
            at=utc_now(),
            actor=_text("actor", actor),
            action=action,
            entity=entity,
            entity_id=str(entity_id),
            details=normalise(dict(details)),
            prev_sha256=prev or GENESIS_SHA256,
        )
        event.sha256 = sha256_hex(audit_content(event))
        s.add(event)
        s.flush()
        append_for_audit(s, event)  # the LIMS feed and webhook outbox, in this same transaction
        return event

    def audit_events(self, *, entity: str | None = None, entity_id: object = None, limit: int = 1000) -> list[AuditEvent]:
        with self._read() as s:
            stmt = sa.select(AuditEvent).order_by(AuditEvent.id.desc()).limit(limit)
            if entity is not None:
                stmt = stmt.where(AuditEvent.entity == entity)
            if entity_id is not None:
                stmt = stmt.where(AuditEvent.entity_id == str(entity_id))
            return list(s.scalars(stmt))

    # ------------------------------------------------------------ lookups inside a transaction

    def _device(self, s: Session, device_id: int) -> Device:
        device = s.get(Device, device_id) if isinstance(device_id, int) else None
        if device is None:
            raise UnknownEntity(f"device {device_id!r} does not exist")
        return device


    def _job(self, s: Session, job_id: int) -> CalibrationJob:
        job = s.get(CalibrationJob, job_id) if isinstance(job_id, int) else None
        if job is None:
            raise UnknownEntity(f"job {job_id!r} does not exist")
        return job

