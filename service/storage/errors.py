"""Storage errors. Refused writes are input errors: the CLI exits 2, the API answers 422 or 409."""

from __future__ import annotations

from service.errors import InputError


class RefusedWrite(InputError):
    """A write that would break the records' rules; nothing of it was stored."""


class UnknownEntity(RefusedWrite):
    """The write names a device, bench, job or record that does not exist."""


class IllegalTransition(RefusedWrite):
    """A job state change the state machine does not allow."""


class ConflictError(RefusedWrite):
    """The write conflicts with the current state (e.g. a second active pointer); re-read and
    retry."""


class RecordNotUsable(ConflictError):
    """A record that must never correct a reading: rejected, or its stored content no longer matches
    its hash."""


class AppendOnlyViolation(RefusedWrite):
    """An update or delete of an append-only row (calibration records, audit events, ...)."""


class SampleWriteError(RuntimeError):
    """The sample writer could not store some samples it had accepted."""


class BackPressureTimeout(TimeoutError):
    """The sample queue stayed full for the whole put timeout: the database cannot keep up."""
