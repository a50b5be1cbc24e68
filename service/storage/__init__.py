"""Persistence: calibration records, jobs, raw samples and the audit log (SQLite or PostgreSQL).

Start-up: `engine = bootstrap(settings)`; then `Store(engine)` for records and actions (one
repository per aggregate: `store.records`, `store.jobs`, ...) and `SampleWriter(engine)` for the
sample stream. Does not import the physics or calibration code.
"""

from service.storage.engine import make_engine, write_engine
from service.storage.errors import (
    AppendOnlyViolation,
    BackPressureTimeout,
    ConflictError,
    IllegalTransition,
    RefusedWrite,
    SampleWriteError,
    UnknownEntity,
)
from service.storage.migrate import bootstrap, current_revision, downgrade, head_revision, upgrade
from service.storage.samples import Sample, apply_retention, insert_samples, latest_samples
from service.storage.store import Store
from service.storage.verify import VerifyReport, verify
from service.storage.writer import SampleWriter

__all__ = [
    "AppendOnlyViolation",
    "BackPressureTimeout",
    "ConflictError",
    "IllegalTransition",
    "RefusedWrite",
    "Sample",
    "SampleWriteError",
    "SampleWriter",
    "Store",
    "UnknownEntity",
    "VerifyReport",
    "apply_retention",
    "bootstrap",
    "current_revision",
    "downgrade",
    "head_revision",
    "insert_samples",
    "latest_samples",
    "make_engine",
    "upgrade",
    "verify",
    "write_engine",
]
