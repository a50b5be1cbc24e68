"""Rows a result depends on that may change over their life (tokens, reference standards, webhook
endpoints): each carries the SHA-256 of all its columns, and every change to it is anchored in the
audit chain.

The rule (content format 1, canonical JSON as in canonical.py): `row_sha256 = SHA-256(canonical JSON
of {column: value})` over **every column of the table but `row_sha256` itself**, a column whose
value is NULL left out; times as ISO 8601 UTC with microseconds and `Z`, dates as `YYYY-MM-DD`. A
column added to one of these tables later joins the hash by itself; NULL in the rows that existed
before, it leaves their hashes as they were (a migration that fills old rows with a value must set
their `row_sha256` again, and anchor it, as 0008 does for the rows it found).

The anchor: the write that creates or changes such a row audits it in the same transaction, and the
audit event's details carry the row's new hash (`rows_sha256`: {"table:id": sha256}). `db verify`
recomputes each row's hash, compares it with the stored one (an edit of a column: TAMPERED) and with
the newest one the audit chain recorded for the row (an edit whose hash was recomputed: TAMPERED;
no record of the row at all: MISSING).
"""

from __future__ import annotations

import datetime as dt
from typing import Any

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.orm import Session

from service.storage.canonical import sha256_hex, utc_iso
from service.storage.models import ApiToken, Base, ReferenceStandard, WebhookEndpoint

HASHED_CLASSES: tuple[type[Base], ...] = (ApiToken, ReferenceStandard, WebhookEndpoint)
HASH_COLUMN = "row_sha256"
ANCHORS = "rows_sha256"  # the key of an audit event's details that carries the rows' hashes
_PENDING = "tiltlab_rows_to_hash"


def _value(value: Any) -> Any:
    if isinstance(value, dt.datetime):
        return utc_iso(value)
    if isinstance(value, dt.date):
        return value.isoformat()
    return value


def row_content(table: sa.Table, values: Any) -> dict[str, object]:
    """What a row's hash covers, from anything with the columns as attributes (an ORM row, a
    Row)."""
    out: dict[str, object] = {}
    for column in table.columns:
        if column.name == HASH_COLUMN:
            continue
        value = getattr(values, column.key if hasattr(values, column.key) else column.name)
        if value is not None:
            out[column.name] = _value(value)
    return out


def row_sha256(obj: Base) -> str:
    return sha256_hex(row_content(obj.__table__, obj))  # type: ignore[arg-type]


def anchor_key(obj: Base) -> str:
    return f"{obj.__tablename__}:{obj.id}"  # type: ignore[attr-defined]


def _changed_rows(session: Session) -> set[Base]:
    """Rows of the hashed tables added, or changed since they were hashed, in this session."""
    changed: set[Base] = {obj for obj in session.new if isinstance(obj, HASHED_CLASSES)}
    for obj in session.dirty:
        if (
            isinstance(obj, HASHED_CLASSES)
            and session.is_modified(obj)
            and getattr(obj, HASH_COLUMN) != row_sha256(obj)
        ):
            changed.add(obj)
    return changed


@event.listens_for(Session, "before_flush")
def _note_changed_rows(session: Session, flush_context: Any, instances: Any) -> None:
    """Rows of the hashed tables added or changed in this transaction, for the audit writer to
    hash."""
    session.info.setdefault(_PENDING, set()).update(_changed_rows(session))


@event.listens_for(Session, "before_commit")
def _refuse_unanchored_changes(session: Session) -> None:
    """A change to a hashed row that no audit event anchors would read as tampering: refused in the
    code."""
    pending = session.info.get(_PENDING, set()) | _changed_rows(session)
    if pending:
        names = ", ".join(
            sorted(f"{row.__tablename__} id={getattr(row, 'id', None)}" for row in pending)
        )
        session.info.pop(_PENDING, None)
        raise RuntimeError(
            f"{names} changed without an audit event in the same transaction: every change of these"
            " rows is audited, with its hash (service/storage/rowhash.py)"
        )


@event.listens_for(Session, "after_rollback")
def _forget(session: Session) -> None:
    session.info.pop(_PENDING, None)


def hash_pending(session: Session) -> dict[str, str]:
    """Hash the rows changed since the last audit event of this transaction (their ids are known:
    the caller flushed); returns {"table:id": sha256} for the audit event to carry."""
    pending: set[Base] = session.info.pop(_PENDING, set())
    anchors: dict[str, str] = {}
    for obj in pending:
        if obj in session.deleted:
            continue
        sha = row_sha256(obj)
        setattr(obj, HASH_COLUMN, sha)
        anchors[anchor_key(obj)] = sha
    return dict(sorted(anchors.items()))
