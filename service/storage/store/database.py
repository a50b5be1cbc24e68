"""The one database every repository shares: its engine, read sessions, serialised write
transactions and the one audit writer that appends to the audit hash chain.

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
from service.storage.feed import append_for_audit
from service.storage.models import GENESIS_SHA256, AuditEvent, utc_now
from service.storage.rowhash import ANCHORS, hash_pending
from service.storage.store.checks import require_text, translate_refusal
from service.storage.store.hashing import audit_content

PG_WRITE_LOCK = 0x7417_1AB1


class Database:
    """One engine, its sessions and the audit writer; every repository holds the same one."""

    def __init__(self, engine: sa.Engine) -> None:
        self.engine = engine
        self._read = sessionmaker(bind=engine, expire_on_commit=False)
        self._write = sessionmaker(bind=write_engine(engine), expire_on_commit=False)

    @contextmanager
    def session(self) -> Iterator[Session]:
        """A read session (or for callers composing their own work; flushes still pass the
        append-only guard)."""
        with self._read() as session:
            yield session

    @contextmanager
    def transaction(self) -> Iterator[Session]:
        """One serialised write transaction; the database's refusals come out as our errors."""
        with self._write() as session:
            try:
                with session.begin():
                    if session.get_bind().dialect.name == "postgresql":
                        session.execute(
                            sa.text("SELECT pg_advisory_xact_lock(:k)"), {"k": PG_WRITE_LOCK}
                        )
                    yield session
            # the guard triggers' refusals included
            except (sa.exc.IntegrityError, sa.exc.DataError) as exc:
                raise translate_refusal(exc) from exc

    def audit(
        self,
        session: Session,
        actor: str,
        action: str,
        entity: str,
        entity_id: object,
        details: Mapping[str, object],
    ) -> AuditEvent:
        """Append an audit event to the chain inside the action's own transaction (and so its feed
        event). The rows of the hashed tables the action added or changed get their new hash, which
        the event records."""
        session.flush()  # the action's rows first, so their ids are known and constraints have run
        # the new hashes of tokens, standards, webhooks this action changed
        anchors = hash_pending(session)
        if anchors:
            details = {**details, ANCHORS: anchors}
        prev = session.execute(
            sa.select(AuditEvent.sha256).order_by(AuditEvent.id.desc()).limit(1)
        ).scalar()
        event = AuditEvent(
            at=utc_now(),
            actor=require_text("actor", actor),
            action=action,
            entity=entity,
            entity_id=str(entity_id),
            details=normalise(dict(details)),
            prev_sha256=prev or GENESIS_SHA256,
        )
        event.sha256 = sha256_hex(audit_content(event))
        session.add(event)
        session.flush()
        # the LIMS feed and webhook outbox, in this same transaction
        append_for_audit(session, event)
        return event
