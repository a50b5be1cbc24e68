"""Tokens, reference standards and webhook endpoints carry the hash of all their columns; settled
points the hash of the raw samples they were averaged from.

Revision ID: 0008_tamper_evident
Revises: 0007_certs_people
Create Date: 2026-12-01

`row_sha256` (api_tokens, reference_standards, webhook_endpoints) is the SHA-256 of the canonical
JSON of every other column of the row, NULL columns left out; each change of such a row is audited
with its new hash, which anchors it in the audit chain. The rows that exist already are hashed here
and anchored by one audit event `rows.hash` (actor `migration 0008`). `samples_sha256`
(settled_points) is the SHA-256 of the point's raw samples; points stored before stay without it
(their records committed to the points alone). The hashing rules are frozen here as they are at this
revision.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
from collections.abc import Sequence
from typing import Any

import sqlalchemy as sa
from alembic import op

revision: str = "0008_tamper_evident"
down_revision: str | Sequence[str] | None = "0007_certs_people"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

HASHED = ("api_tokens", "reference_standards", "webhook_endpoints")
GENESIS = "0" * 64
ACTOR = "migration 0008"


def _utc(value: dt.datetime) -> str:
    if value.tzinfo is None:
        value = value.replace(tzinfo=dt.UTC)
    return value.astimezone(dt.UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _value(value: Any) -> Any:
    if isinstance(value, dt.datetime):
        return _utc(value)
    if isinstance(value, dt.date):
        return value.isoformat()
    return value


def _sha(value: Any) -> str:
    text = json.dumps(
        value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False
    )
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def upgrade() -> None:
    for table in HASHED:
        op.add_column(table, sa.Column("row_sha256", sa.String(length=64), nullable=True))
    op.add_column(
        "settled_points", sa.Column("samples_sha256", sa.String(length=64), nullable=True)
    )
    if op.get_context().as_sql:  # an offline SQL script is for a new database: no rows to hash yet
        return
    bind = op.get_bind()
    anchors: dict[str, str] = {}
    for name in HASHED:
        table = sa.Table(name, sa.MetaData(), autoload_with=bind)
        for row in bind.execute(sa.select(table)).mappings().all():
            content = {k: _value(v) for k, v in row.items() if k != "row_sha256" and v is not None}
            sha = _sha(content)
            bind.execute(sa.update(table).where(table.c.id == row["id"]).values(row_sha256=sha))
            anchors[f"{name}:{row['id']}"] = sha
    if anchors:
        _audit(bind, dict(sorted(anchors.items())))


def _audit(bind: sa.Connection, anchors: dict[str, str]) -> None:
    """One audit event recording the hashes of the rows found, chained after the newest event."""
    events = sa.table(
        "audit_events",
        sa.column("id", sa.BigInteger()),
        sa.column("at", sa.DateTime(timezone=True)),
        sa.column("actor", sa.String()),
        sa.column("action", sa.String()),
        sa.column("entity", sa.String()),
        sa.column("entity_id", sa.String()),
        sa.column("details", sa.JSON()),
        sa.column("prev_sha256", sa.String()),
        sa.column("sha256", sa.String()),
    )
    prev = (
        bind.execute(sa.select(events.c.sha256).order_by(events.c.id.desc()).limit(1)).scalar()
        or GENESIS
    )
    at = dt.datetime.now(dt.UTC)
    details = {"rows_sha256": anchors, "reason": "rows hashed when their hashes were introduced"}
    content = {
        "at": _utc(at),
        "actor": ACTOR,
        "action": "rows.hash",
        "entity": "database",
        "entity_id": "0",
        "details": details,
        "prev_sha256": prev,
    }
    stored_at = at.replace(tzinfo=None) if bind.dialect.name == "sqlite" else at
    bind.execute(
        sa.insert(events).values(
            at=stored_at,
            actor=ACTOR,
            action="rows.hash",
            entity="database",
            entity_id="0",
            details=details,
            prev_sha256=prev,
            sha256=_sha(content),
        )
    )


def downgrade() -> None:
    for table in (*HASHED, "settled_points"):
        column = "samples_sha256" if table == "settled_points" else "row_sha256"
        if (
            op.get_context().dialect.name == "sqlite"
        ):  # natively (a batch copy would drop the table's triggers)
            op.execute(f"ALTER TABLE {table} DROP COLUMN {column}")
        else:
            op.drop_column(table, column)
