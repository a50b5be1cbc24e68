"""Input checks shared by the write methods, and the translation of database refusals into our
errors."""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping

import sqlalchemy as sa

from service.errors import InputError
from service.storage.canonical import normalise
from service.storage.errors import AppendOnlyViolation, ConflictError, RefusedWrite, UnknownEntity


def require_text(name: str, value: object, max_len: int = 100) -> str:
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"{name} must be a non-empty string")
    if len(value) > max_len:
        raise InputError(f"{name} is longer than {max_len} characters")
    return value


def optional_text(name: str, value: object, max_len: int) -> str | None:
    return None if value is None else require_text(name, value, max_len)


def require_finite(name: str, value: object, *, optional: bool = True) -> float | None:
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise InputError(f"{name}={value!r} is not a finite number")
    return float(value)


def require_number(name: str, value: object) -> float:
    """A finite number that must be given."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise InputError(f"{name}={value!r} is not a finite number")
    return float(value)


def require_date(name: str, value: object) -> dt.date:
    if isinstance(value, dt.datetime):
        raise InputError(f"{name}: a date (YYYY-MM-DD) is needed, not a time")
    if isinstance(value, dt.date):
        return value
    if isinstance(value, str):
        try:
            return dt.date.fromisoformat(value)
        except ValueError:
            pass
    raise InputError(f"{name}: {value!r} is not a date (YYYY-MM-DD)")


def require_doc(name: str, value: object) -> dict[str, object]:
    """A JSON object as it will be stored and read back (its shape is the caller's)."""
    if not isinstance(value, Mapping):
        raise InputError(f"{name} must be a JSON object (dict)")
    doc: dict[str, object] = normalise(dict(value))
    return doc


def require_standards(value: object) -> list[dict[str, object]]:
    """The reference standards a record names, as stored: each with a certificate_id and a name or
    a serial."""
    if not isinstance(value, list | tuple):
        raise InputError("reference_standards must be a list of {name, serial, certificate_id}")
    out: list[dict[str, object]] = []
    for i, item in enumerate(value):
        if not isinstance(item, Mapping):
            raise InputError(f"reference_standards[{i}] must be an object")
        cert = item.get("certificate_id")
        if not isinstance(cert, str) or not cert.strip():
            raise InputError(
                f"reference_standards[{i}] has no certificate_id: traceability needs it"
            )
        if not (item.get("name") or item.get("serial")):
            raise InputError(f"reference_standards[{i}] needs a name or a serial")
        out.append(dict(item))
    checked: list[dict[str, object]] = normalise(out)
    return checked


def translate_refusal(exc: sa.exc.DBAPIError) -> RefusedWrite:
    orig = exc.orig
    message = str(orig).strip().splitlines()[0] if orig is not None else str(exc)
    code = getattr(orig, "sqlstate", None)
    lower = message.lower()
    if "append-only" in lower or "raw data" in lower or "are kept" in lower:
        return AppendOnlyViolation(f"refused by the database: {message}")
    if code == "23503" or "foreign key" in lower:
        return UnknownEntity(
            f"refused by the database: a referenced row does not exist ({message})"
        )
    if code == "23505" or "unique" in lower:
        return ConflictError(f"refused by the database: duplicate ({message})")
    return RefusedWrite(f"refused by the database: {message}")
