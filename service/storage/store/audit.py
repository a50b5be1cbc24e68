"""The audit log: reading it, and an event for an action that changes no row."""

from __future__ import annotations

from collections.abc import Mapping

import sqlalchemy as sa

from service.storage.models import AuditEvent
from service.storage.store.database import Database


class AuditRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def events(
        self, *, entity: str | None = None, entity_id: object = None, limit: int = 1000
    ) -> list[AuditEvent]:
        with self._db.session() as session:
            stmt = sa.select(AuditEvent).order_by(AuditEvent.id.desc()).limit(limit)
            if entity is not None:
                stmt = stmt.where(AuditEvent.entity == entity)
            if entity_id is not None:
                stmt = stmt.where(AuditEvent.entity_id == str(entity_id))
            return list(session.scalars(stmt))

    def action(
        self, actor: str, action: str, entity: str, entity_id: object, details: Mapping[str, object]
    ) -> None:
        """An audit event for an action that changes no row (a stage move, a stop)."""
        with self._db.transaction() as session:
            self._db.audit(session, actor, action, entity, entity_id, details)
