"""The repository of the lab's records: every state-changing action is one transaction plus its audit event.

Each write method checks its input, writes, appends the audit event and commits, or leaves
nothing behind. One module per concern: sessions and the audit chain (base), benches and devices,
jobs, settled points, calibration records, the active pointer, retention; `Store` is all of them.
"""

from __future__ import annotations

from service.storage.store.activation import ActivationStore
from service.storage.store.base import StoreBase
from service.storage.store.checks import _doc, _finite, _optional_text, _standards, _text, _translate
from service.storage.store.devices import DevicesStore
from service.storage.store.hashing import (
    _POINT_FIELDS,
    _POINT_REQUIRED,
    audit_content,
    point_content,
    points_sha256,
    record_content,
)
from service.storage.store.jobs import TERMINAL, TRANSITIONS, JobsStore
from service.storage.store.points import PointsStore, _mean, _std
from service.storage.store.records import _UNSET, RecordsStore
from service.storage.store.retention import RetentionStore


class Store(DevicesStore, JobsStore, PointsStore, RecordsStore, ActivationStore, RetentionStore, StoreBase):
    """Devices, jobs, settled points, records, the active pointer, retention and the audit log of one database."""


__all__ = [
    "TERMINAL",
    "TRANSITIONS",
    "ActivationStore",
    "DevicesStore",
    "JobsStore",
    "PointsStore",
    "RecordsStore",
    "RetentionStore",
    "Store",
    "StoreBase",
    "_POINT_FIELDS",
    "_POINT_REQUIRED",
    "_UNSET",
    "_doc",
    "_finite",
    "_mean",
    "_optional_text",
    "_standards",
    "_std",
    "_text",
    "_translate",
    "audit_content",
    "point_content",
    "points_sha256",
    "record_content",
]
