"""Canonical JSON and SHA-256: the rule every stored hash is computed with.

Rule (content_format 1): UTF-8 JSON with keys sorted, no insignificant whitespace
(separators "," and ":"), non-ASCII kept as is, floats in Python's shortest round-trip
repr, NaN and infinities refused, tuples as lists, times as ISO 8601 UTC with
microseconds and a trailing "Z". Values are normalised through this same encoding
before they are stored, so what is stored is exactly what was hashed.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import math
from typing import Any

from service.errors import InputError


def utc_iso(value: dt.datetime) -> str:
    if value.tzinfo is None:
        value = value.replace(tzinfo=dt.UTC)
    return value.astimezone(dt.UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _default(value: Any) -> Any:
    if isinstance(value, dt.datetime):
        return utc_iso(value)
    if hasattr(value, "tolist"):  # array-likes from numeric code, without importing numpy here
        return value.tolist()
    if hasattr(value, "item"):
        return value.item()
    raise TypeError(f"not JSON-serialisable: {type(value).__name__}")


def _check_finite(value: Any, path: str) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        raise InputError(f"{path}: {value} is not a finite number; stored content must be finite")
    if isinstance(value, dict):
        for k, child in value.items():
            _check_finite(child, f"{path}.{k}")
    elif isinstance(value, list | tuple):
        for i, child in enumerate(value):
            _check_finite(child, f"{path}[{i}]")


def canonical_json(value: Any) -> str:
    try:
        text = json.dumps(
            value,
            sort_keys=True,
            separators=(",", ":"),
            ensure_ascii=False,
            allow_nan=False,
            default=_default,
        )
    except ValueError:
        _check_finite(json.loads(json.dumps(value, default=_default)), "content")
        raise
    except TypeError as exc:
        raise InputError(f"content cannot be stored as JSON: {exc}") from exc
    return text


def normalise(value: Any) -> Any:
    """The value as it will read back from the database (what gets hashed)."""
    return json.loads(canonical_json(value))


def sha256_hex(value: Any) -> str:
    return hashlib.sha256(canonical_json(value).encode("utf-8")).hexdigest()
