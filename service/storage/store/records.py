"""Calibration records: append-only versions per (device, kind), hash-chained, optionally activated
at once."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, TypedDict

import sqlalchemy as sa
from sqlalchemy.orm import Session, defer

from service.errors import InputError
from service.storage.canonical import sha256_hex
from service.storage.errors import IllegalTransition, UnknownEntity
from service.storage.models import (
    GENESIS_SHA256,
    ActiveCalibration,
    ActiveCalibrationHistory,
    CalibrationRecord,
    JobState,
    SettledPoint,
    utc_now,
)
from service.storage.models import Sample as SampleRow
from service.storage.store.checks import (
    require_doc,
    require_finite,
    require_standards,
    require_text,
)
from service.storage.store.database import Database
from service.storage.store.hashing import points_sha256, record_content
from service.storage.store.lookups import device_in, job_in, row_in
from service.storage.store.pointer import activate_in, deactivate_in, unusable_in

SUPERSEDES_ACTIVE: Any = object()  # a new version supersedes whichever version is active


class JobRawData(TypedDict):
    """What a record made by a job keeps of the job's data in its `raw_data`."""

    job_id: int
    points: int
    points_sha256: str
    samples: int | None
    settled_points_sha256: dict[str, str]  # by device id (as text)


class RecordsRepo:
    """Calibration records and the active pointer of each (device, kind)."""

    def __init__(self, db: Database) -> None:
        self._db = db

    def add_record(
        self,
        device_id: int,
        kind: str,
        method: str,
        model: Mapping[str, object],
        *,
        operator: str,
        reference_standards: Sequence[Mapping[str, object]] = (),
        validation: Mapping[str, object] | None = None,
        temp_c: float | None = None,
        job_id: int | None = None,
        raw_data: Mapping[str, object] | None = None,
        supersedes_id: int | None = SUPERSEDES_ACTIVE,
        activate: bool = False,
        reason: str | None = None,
    ) -> CalibrationRecord:
        """Append a new version for (device, kind). By default it supersedes the active version.

        With activate=True the new version also becomes the active one in the same transaction.
        """
        with self._db.transaction() as session:
            device_in(session, device_id)
            kind, method = require_text("kind", kind, 40), require_text("method", method, 80)
            operator = require_text("operator", operator)
            model_doc = require_doc("model", model)
            _check_model_names(model_doc, kind, method)
            raw = require_doc("raw_data", raw_data or {})
            if job_id is not None:
                raw.update(_job_raw_data(session, job_id, device_id))
            active = session.get(ActiveCalibration, (device_id, kind))
            supersedes_id = _superseded_id(session, supersedes_id, active, device_id, kind)
            last = session.execute(
                sa.select(CalibrationRecord.version, CalibrationRecord.content_sha256)
                .where(CalibrationRecord.device_id == device_id, CalibrationRecord.kind == kind)
                .order_by(CalibrationRecord.version.desc())
                .limit(1)
            ).first()
            record = CalibrationRecord(
                device_id=device_id,
                kind=kind,
                version=(last.version + 1) if last else 1,
                content_format=1,
                method=method,
                model=model_doc,
                validation=require_doc("validation", validation or {}),
                temp_c=require_finite("temp_c", temp_c),
                reference_standards=require_standards(list(reference_standards)),
                operator=operator,
                created_at=utc_now(),
                job_id=job_id,
                raw_data=raw,
                supersedes_id=supersedes_id,
                prev_sha256=last.content_sha256 if last else GENESIS_SHA256,
            )
            record.content_sha256 = sha256_hex(record_content(record))
            session.add(record)
            session.flush()
            self._db.audit(
                session,
                operator,
                "record.create",
                "calibration_record",
                record.id,
                {
                    "device_id": device_id,
                    "kind": kind,
                    "version": record.version,
                    "content_sha256": record.content_sha256,
                    "supersedes_id": supersedes_id,
                },
            )
            if activate:
                activate_in(
                    self._db,
                    session,
                    record,
                    actor=operator,
                    reason=reason or f"new version {record.version}",
                    replaces=active.record_id if active else None,
                )
            return record

    def get_record(self, record_id: int) -> CalibrationRecord:
        with self._db.session() as session:
            return row_in(session, CalibrationRecord, record_id, "calibration record")

    def records_of_jobs(self, job_ids: Sequence[int]) -> dict[int, CalibrationRecord]:
        """The record each of these jobs made, the first made from its points (an adopted diagnosis
        adds later versions); jobs that made none are left out. One query."""
        if not job_ids:
            return {}
        out: dict[int, CalibrationRecord] = {}
        with self._db.session() as session:
            for record in session.scalars(
                sa.select(CalibrationRecord)
                .where(CalibrationRecord.job_id.in_(list(job_ids)))
                .order_by(CalibrationRecord.id)
            ):
                if record.job_id is not None:
                    out.setdefault(record.job_id, record)
        return out

    def fitted_ranges(self, record_ids: Sequence[int]) -> dict[int, Any]:
        """The table tilts each record's model says it was fitted on (MODEL.json
        `fit.table_tilt_range_deg`, as stored; None where the model has none), read out of the
        models by the database, not decoded here."""
        if not record_ids:
            return {}
        fitted = CalibrationRecord.model["fit"]["table_tilt_range_deg"]
        with self._db.session() as session:
            rows = session.execute(
                sa.select(CalibrationRecord.id, fitted).where(
                    CalibrationRecord.id.in_(list(record_ids))
                )
            )
            return {int(i): value for i, value in rows}

    def active_record_ids(self) -> set[int]:
        """The ids of every record in use (one per device and kind)."""
        with self._db.session() as session:
            return set(session.scalars(sa.select(ActiveCalibration.record_id)))

    def of_device(self, device_id: int, kind: str | None = None) -> list[CalibrationRecord]:
        with self._db.session() as session:
            stmt = sa.select(CalibrationRecord).where(CalibrationRecord.device_id == device_id)
            if kind is not None:
                stmt = stmt.where(CalibrationRecord.kind == kind)
            return list(
                session.scalars(stmt.order_by(CalibrationRecord.kind, CalibrationRecord.version))
            )

    def newest_first(
        self,
        *,
        device_id: int | None = None,
        device_ids: Sequence[int] | None = None,
        before_id: int | None = None,
        limit: int | None = None,
        with_model: bool = True,
    ) -> list[CalibrationRecord]:
        """Records newest first, of one device, of some devices (None: of every device), or both
        filters; `before_id` is the cursor (the last id of the previous page), `limit` the page
        size. Without the model (`with_model=False`) a page costs a fraction of the decoding: the
        model is most of a record."""
        stmt = sa.select(CalibrationRecord).order_by(CalibrationRecord.id.desc())
        if not with_model:
            stmt = stmt.options(defer(CalibrationRecord.model, raiseload=True))
        if before_id is not None:
            stmt = stmt.where(CalibrationRecord.id < before_id)
        if limit is not None:
            stmt = stmt.limit(limit)
        if device_id is not None:
            stmt = stmt.where(CalibrationRecord.device_id == device_id)
        if device_ids is not None:
            stmt = stmt.where(CalibrationRecord.device_id.in_(list(device_ids)))
        with self._db.session() as session:
            return list(session.scalars(stmt))

    def active_record(self, device_id: int, kind: str) -> CalibrationRecord | None:
        with self._db.session() as session:
            return session.scalar(
                sa.select(CalibrationRecord)
                .join(ActiveCalibration, ActiveCalibration.record_id == CalibrationRecord.id)
                .where(ActiveCalibration.device_id == device_id, ActiveCalibration.kind == kind)
            )

    def pointer_history(self, device_id: int, kind: str) -> list[ActiveCalibrationHistory]:
        with self._db.session() as session:
            return list(
                session.scalars(
                    sa.select(ActiveCalibrationHistory)
                    .where(
                        ActiveCalibrationHistory.device_id == device_id,
                        ActiveCalibrationHistory.kind == kind,
                    )
                    .order_by(ActiveCalibrationHistory.id)
                )
            )

    def activate(
        self, record_id: int, *, actor: str, reason: str, replaces: int | None = None
    ) -> ActiveCalibration:
        """Make a record the active version of its (device, kind).

        `replaces` names the record the caller believes is active now (None: none is). If another
        one is active the change is refused: there is never a second active pointer, and a switch
        is always a deliberate, audited act.
        """
        with self._db.transaction() as session:
            record = row_in(session, CalibrationRecord, record_id, "calibration record")
            return activate_in(
                self._db, session, record, actor=actor, reason=reason, replaces=replaces
            )

    def unusable_reason(self, record_id: int) -> str | None:
        """Why the record must not correct anything (rejected, or not matching its hash), or None if
        it may."""
        with self._db.session() as session:
            return unusable_in(
                session, row_in(session, CalibrationRecord, record_id, "calibration record")
            )

    def inactive_reason(self, device_id: int, kind: str) -> str | None:
        """Why (device, kind) has no active record, when its pointer was withdrawn: the reason of
        that change."""
        with self._db.session() as session:
            last = session.scalar(
                sa.select(ActiveCalibrationHistory)
                .where(
                    ActiveCalibrationHistory.device_id == device_id,
                    ActiveCalibrationHistory.kind == kind,
                )
                .order_by(ActiveCalibrationHistory.id.desc())
                .limit(1)
            )
        if last is None or last.record_id is not None:
            return None
        return (
            f"record {last.previous_record_id} was deactivated by {last.changed_by}: {last.reason}"
        )

    def deactivate(
        self, device_id: int, kind: str, *, actor: str, reason: str, replaces: int
    ) -> None:
        """Withdraw the active version (e.g. the device failed validation); audited like a
        switch."""
        with self._db.transaction() as session:
            deactivate_in(
                self._db, session, device_id, kind, actor=actor, reason=reason, replaces=replaces
            )


def _check_model_names(model_doc: Mapping[str, object], kind: str, method: str) -> None:
    """A model document that names its kind or method must name the record's."""
    for key, expected in (("kind", kind), ("method", method)):
        if key in model_doc and model_doc[key] != expected:
            raise InputError(
                f"model document says {key}={model_doc[key]!r} but the record is {expected!r}"
            )


def _job_raw_data(session: Session, job_id: int, device_id: int) -> JobRawData:
    """What a record made by a job keeps of the job's data: its points and their hashes, its count
    of samples; the job must calibrate this device and be running or done."""
    job = job_in(session, job_id)
    if job.device_id != device_id:
        raise InputError(f"job {job_id} calibrates device {job.device_id}, not device {device_id}")
    if job.state not in (JobState.RUNNING, JobState.SUCCEEDED):
        raise IllegalTransition(
            f"job {job_id} is {job.state}; a record comes from a running or succeeded job"
        )
    pts = list(
        session.scalars(
            sa.select(SettledPoint).where(
                SettledPoint.job_id == job_id, SettledPoint.device_id == device_id
            )
        )
    )
    n_samples = session.scalar(
        sa.select(sa.func.count())
        .select_from(SampleRow)
        .where(SampleRow.job_id == job_id, SampleRow.device_id == device_id)
    )
    return {
        "job_id": job_id,
        "points": len(pts),
        "points_sha256": points_sha256(pts),
        "samples": n_samples,
        "settled_points_sha256": _points_by_device_sha256(session, job_id),
    }


def _superseded_id(
    session: Session,
    supersedes_id: int | None,
    active: ActiveCalibration | None,
    device_id: int,
    kind: str,
) -> int | None:
    """The version a new record supersedes: the active one by default, else one given of the same
    device and kind (or none)."""
    if supersedes_id is SUPERSEDES_ACTIVE:
        return active.record_id if active else None
    if supersedes_id is not None:
        old = session.get(CalibrationRecord, supersedes_id)
        if old is None or (old.device_id, old.kind) != (device_id, kind):
            raise UnknownEntity(
                f"record {supersedes_id} is not a {kind} record of device {device_id}"
            )
    return supersedes_id


def _points_by_device_sha256(session: Session, job_id: int) -> dict[str, str]:
    """The SHA-256 of every device's settled points in the job (the reference sensor's too: a fit
    uses them), keyed by device id: what `db verify` checks the job's points against."""
    by_device: dict[int, list[SettledPoint]] = {}
    for point in session.scalars(sa.select(SettledPoint).where(SettledPoint.job_id == job_id)):
        by_device.setdefault(point.device_id, []).append(point)
    return {str(device): points_sha256(pts) for device, pts in sorted(by_device.items())}
