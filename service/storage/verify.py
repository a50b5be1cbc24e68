"""Integrity check of calibration records and the audit log, from the database alone.

A record or event whose content does not hash to its stored SHA-256 is *tampered*; one whose
predecessor hash does not match the stored hash of the row before it (or whose predecessor is
missing) is a *broken chain*. Record creations are also cross-checked with their audit events,
which catches the removal of the newest version of a chain; so are approvals and rejections, which
catches the removal of the newest decision (the approvals' own chain cannot see its end). A
record made by a job is checked against the settled points of every device of that job (the
reference sensor's included: the fit used them), and each settled point against the raw samples it
was averaged from (their hash is part of the point's content, and so of the record's). Tokens,
reference standards and webhook endpoints are checked against their row hash and against the newest
hash the audit chain recorded for them (service/storage/rowhash.py). The newest audit event can only
be vouched for against a copy of its hash kept elsewhere: the report prints it for that purpose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import sqlalchemy as sa
from sqlalchemy.orm import Session

from service.storage.canonical import sha256_hex
from service.storage.models import GENESIS_SHA256, AuditEvent, CalibrationRecord, SettledPoint
from service.storage.models import Sample as SampleRow
from service.storage.rowhash import ANCHORS, HASH_COLUMN, HASHED_CLASSES, anchor_key, row_sha256
from service.storage.store.hashing import (
    SAMPLE_FIELDS,
    audit_content,
    points_sha256,
    record_content,
    samples_sha256,
)


@dataclass(frozen=True)
class Problem:
    table: str
    row_id: int | None
    kind: str  # "tampered" | "broken_chain" | "missing" | "raw_data_changed"
    detail: str

    def __str__(self) -> str:
        where = f"{self.table} id={self.row_id}" if self.row_id is not None else self.table
        return f"{self.kind.upper()}: {where}: {self.detail}"


@dataclass
class VerifyReport:
    records_checked: int = 0
    audit_events_checked: int = 0
    approvals_checked: int = 0
    rows_checked: int = 0
    sample_points_checked: int = 0
    audit_head_sha256: str = GENESIS_SHA256
    problems: list[Problem] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    @property
    def tampered(self) -> list[Problem]:
        return [problem for problem in self.problems if problem.kind == "tampered"]

    @property
    def broken(self) -> list[Problem]:
        return [problem for problem in self.problems if problem.kind != "tampered"]

    def lines(self) -> list[str]:
        out = [
            f"calibration records checked: {self.records_checked}",
            f"audit events checked: {self.audit_events_checked}",
            f"approvals and rejections checked: {self.approvals_checked}",
            f"tokens, reference standards and webhook endpoints checked: {self.rows_checked}",
            f"settled points checked against their raw samples: {self.sample_points_checked}",
            f"audit head sha256: {self.audit_head_sha256}",
        ]
        out += [str(problem) for problem in self.problems]
        out.append(
            "OK: every hash and chain link verifies"
            if self.ok
            else f"FAILED: {len(self.problems)} problem(s)"
        )
        return out


def verify(engine: sa.Engine) -> VerifyReport:
    report = VerifyReport()
    with Session(engine) as session:
        _verify_records(session, report)
        _verify_samples(session, report)
        created, decided, anchors = _verify_audit(session, report)
        _cross_check(session, report, created)
        _verify_approvals_and_certificates(session, report, decided)
        _verify_rows(session, report, anchors)
    return report


def _verify_records(session: Session, report: VerifyReport) -> None:
    records = session.scalars(
        sa.select(CalibrationRecord).order_by(
            CalibrationRecord.device_id, CalibrationRecord.kind, CalibrationRecord.version
        )
    )
    prev: CalibrationRecord | None = None
    for record in records:
        report.records_checked += 1
        if sha256_hex(record_content(record)) != record.content_sha256:
            report.problems.append(
                Problem(
                    "calibration_records",
                    record.id,
                    "tampered",
                    f"device {record.device_id} {record.kind} v{record.version}: content does not "
                    "match its SHA-256",
                )
            )
        same_chain = prev is not None and (prev.device_id, prev.kind) == (
            record.device_id,
            record.kind,
        )
        expected_version = prev.version + 1 if same_chain else 1  # type: ignore[union-attr]
        expected_prev = prev.content_sha256 if same_chain else GENESIS_SHA256  # type: ignore[union-attr]
        if record.version != expected_version:
            report.problems.append(
                Problem(
                    "calibration_records",
                    record.id,
                    "broken_chain",
                    f"device {record.device_id} {record.kind}: v{record.version} follows "
                    f"v{expected_version - 1}; a version is missing",
                )
            )
        elif record.prev_sha256 != expected_prev:
            report.problems.append(
                Problem(
                    "calibration_records",
                    record.id,
                    "broken_chain",
                    f"device {record.device_id} {record.kind} v{record.version}: predecessor hash "
                    f"does not match v{record.version - 1}",
                )
            )
        if record.job_id is not None:
            _verify_points(session, report, record)
        prev = record


def _verify_points(session: Session, report: VerifyReport, r: CalibrationRecord) -> None:
    """The job's settled points against the hashes the record holds: every device's (records made
    since the per-device hashes exist), else the record's own device's (older records: all they
    committed to)."""
    by_device = r.raw_data.get("settled_points_sha256")
    if not isinstance(by_device, dict):
        by_device = (
            {str(r.device_id): r.raw_data["points_sha256"]} if "points_sha256" in r.raw_data else {}
        )
    stored = _settled_by_device(session, r.job_id)
    for device, sha in sorted(by_device.items()):
        if points_sha256(stored.get(device, [])) != sha:
            report.problems.append(
                Problem(
                    "calibration_records",
                    r.id,
                    "raw_data_changed",
                    f"the settled points of device {device} in job {r.job_id} no longer hash to "
                    f"what v{r.version} was fitted on",
                )
            )
    if "settled_points_sha256" in r.raw_data:
        for device in sorted(set(stored) - set(by_device)):
            report.problems.append(
                Problem(
                    "calibration_records",
                    r.id,
                    "raw_data_changed",
                    f"job {r.job_id} has settled points of device {device} that v{r.version} did "
                    "not record",
                )
            )
    _verify_measurement_points(session, report, r)


def _settled_by_device(session: Session, job_id: int | None) -> dict[str, list[SettledPoint]]:
    """A job's settled points by device id as text, the keys the records' point hashes use."""
    by_device: dict[str, list[SettledPoint]] = {}
    for point in session.scalars(sa.select(SettledPoint).where(SettledPoint.job_id == job_id)):
        by_device.setdefault(str(point.device_id), []).append(point)
    return by_device


def _verify_measurement_points(
    session: Session, report: VerifyReport, r: CalibrationRecord
) -> None:
    """A version adopted from a diagnosis that measured more points was fitted on those jobs'
    points too: each of them against the hashes the record holds."""
    measured = r.raw_data.get("measurement_points_sha256")
    for job_id, hashes in measured.items() if isinstance(measured, dict) else ():
        held = _settled_by_device(session, int(job_id))
        for device in sorted(set(hashes) | set(held)):
            if device not in hashes or points_sha256(held.get(device, [])) != hashes[device]:
                report.problems.append(
                    Problem(
                        "calibration_records",
                        r.id,
                        "raw_data_changed",
                        f"the settled points of device {device} in measurement job {job_id} no "
                        f"longer hash to what v{r.version} was fitted on",
                    )
                )


_DECISIONS = ("record.approve", "record.review", "record.reject")


# "table:id" -> (the audit event that recorded it last, the row's hash)
Anchors = dict[str, tuple[int, str]]


def _verify_audit(
    session: Session, report: VerifyReport
) -> tuple[dict[int, str], dict[int, tuple[int, str]], Anchors]:
    """Walks the chain in id order; returns record id -> content hash from record.create events,
    approval id -> (audit event id, approval hash) from the decisions' events, and the newest hash
    each hashed row (token, standard, webhook endpoint) was given by the events that changed it."""
    created: dict[int, str] = {}
    decided: dict[int, tuple[int, str]] = {}
    anchors: Anchors = {}
    prev_sha = GENESIS_SHA256
    for event in session.scalars(sa.select(AuditEvent).order_by(AuditEvent.id)).yield_per(1000):
        report.audit_events_checked += 1
        if sha256_hex(audit_content(event)) != event.sha256:
            report.problems.append(
                Problem(
                    "audit_events",
                    event.id,
                    "tampered",
                    f"{event.action} by {event.actor} at {event.at:%Y-%m-%d %H:%M:%S}: content "
                    "does not match its SHA-256",
                )
            )
        if event.prev_sha256 != prev_sha:
            report.problems.append(
                Problem(
                    "audit_events",
                    event.id,
                    "broken_chain",
                    "predecessor hash does not match the previous event; an event was removed or "
                    "altered",
                )
            )
        if event.action == "record.create":
            created[int(event.entity_id)] = str(event.details.get("content_sha256"))
        elif event.action in _DECISIONS and isinstance(event.details.get("approval_id"), int):
            decided[event.details["approval_id"]] = (
                event.id,
                str(event.details.get("approval_sha256")),
            )
        rows = event.details.get(ANCHORS) if isinstance(event.details, dict) else None
        if isinstance(rows, dict):
            anchors.update({str(key): (event.id, str(sha)) for key, sha in rows.items()})
        prev_sha = event.sha256
    report.audit_head_sha256 = prev_sha
    return created, decided, anchors


def _cross_check(session: Session, report: VerifyReport, created: dict[int, str]) -> None:
    stored = {
        rid: sha
        for rid, sha in session.execute(
            sa.select(CalibrationRecord.id, CalibrationRecord.content_sha256)
        )
    }
    for record_id, sha in sorted(created.items()):
        if record_id not in stored:
            report.problems.append(
                Problem(
                    "calibration_records",
                    record_id,
                    "missing",
                    "the audit log records its creation but the record is gone",
                )
            )
        elif stored[record_id] != sha:
            report.problems.append(
                Problem(
                    "calibration_records",
                    record_id,
                    "tampered",
                    "its hash differs from the one recorded in the audit log at creation",
                )
            )
    for record_id in sorted(set(stored) - set(created)):
        report.problems.append(
            Problem(
                "calibration_records", record_id, "missing", "no audit event records its creation"
            )
        )


def _verify_approvals_and_certificates(
    session: Session, report: VerifyReport, decided: dict[int, tuple[int, str]]
) -> None:
    """Approvals: content against hash, the chain, and each against the audit event of its decision
    (the audit chain anchors the approvals' newest end); issued certificates: stored bytes against
    their SHA-256."""
    import hashlib

    from service.storage.canonical import normalise
    from service.storage.models import Certificate, RecordApproval
    from service.storage.store.approvals import approval_content

    prev = GENESIS_SHA256
    for approval in session.scalars(sa.select(RecordApproval).order_by(RecordApproval.id)):
        if sha256_hex(normalise(approval_content(approval))) != approval.sha256:
            report.problems.append(
                Problem(
                    "record_approvals",
                    approval.id,
                    "tampered",
                    f"{approval.decision} of record {approval.record_id} by {approval.actor}: "
                    "content does not match its SHA-256",
                )
            )
        if approval.prev_sha256 != prev:
            report.problems.append(
                Problem(
                    "record_approvals",
                    approval.id,
                    "broken_chain",
                    "predecessor hash does not match the previous approval; one was removed or "
                    "altered",
                )
            )
        audited = decided.pop(approval.id, None)
        if audited is None:
            report.problems.append(
                Problem(
                    "record_approvals",
                    approval.id,
                    "missing",
                    f"no audit event records the {approval.decision} of record "
                    f"{approval.record_id} by {approval.actor}",
                )
            )
        elif audited[1] != approval.sha256:
            report.problems.append(
                Problem(
                    "record_approvals",
                    approval.id,
                    "tampered",
                    f"its hash differs from the one audit event {audited[0]} recorded at the "
                    "decision",
                )
            )
        report.approvals_checked += 1
        prev = approval.sha256
    for approval_id, (event_id, _sha) in sorted(decided.items()):
        event = session.get(AuditEvent, event_id)
        what = (
            f"{event.action} of record {event.entity_id} by {event.actor}"
            if event is not None
            else "a decision"
        )
        report.problems.append(
            Problem(
                "record_approvals",
                approval_id,
                "missing",
                f"audit event {event_id} records {what} but the approval is gone (a record's "
                "status would read as if that decision was never made)",
            )
        )
    for certificate in session.scalars(sa.select(Certificate).order_by(Certificate.id)):
        if hashlib.sha256(certificate.xml).hexdigest() != certificate.sha256:
            report.problems.append(
                Problem(
                    "certificates",
                    certificate.id,
                    "tampered",
                    f"certificate {certificate.number}: stored bytes do not match the SHA-256 "
                    "recorded at issue",
                )
            )


def _what(row: object) -> str:
    """A hashed row in words: which token, standard or endpoint it is."""
    table = row.__tablename__  # type: ignore[attr-defined]
    if table == "api_tokens":
        return f"token {row.name!r}"  # type: ignore[attr-defined]
    if table == "reference_standards":
        return f"standard {row.name!r} serial {row.serial} certificate {row.certificate_number}"  # type: ignore[attr-defined]
    return f"webhook endpoint {row.id}"  # type: ignore[attr-defined]


def _verify_rows(session: Session, report: VerifyReport, anchors: Anchors) -> None:
    """Tokens (scopes, person, revocation ...), reference standards (every field) and webhook
    endpoints: each row against its own hash, and that hash against the newest one the audit chain
    recorded for it."""
    left = dict(anchors)
    for cls in HASHED_CLASSES:
        table = cls.__tablename__
        for row in session.scalars(sa.select(cls).order_by(cls.id)):  # type: ignore[attr-defined]
            report.rows_checked += 1
            stored = getattr(row, HASH_COLUMN)
            audited = left.pop(anchor_key(row), None)
            if stored is None or row_sha256(row) != stored:
                report.problems.append(
                    Problem(
                        table,
                        row.id,  # type: ignore[attr-defined]
                        "tampered",
                        f"{_what(row)}: its columns do not match its SHA-256 (changed outside the "
                        "daemon)",
                    )
                )
            elif audited is None:
                report.problems.append(
                    Problem(
                        table,
                        row.id,  # type: ignore[attr-defined]
                        "missing",
                        f"{_what(row)}: no audit event records it (added outside the daemon)",
                    )
                )
            elif audited[1] != stored:
                report.problems.append(
                    Problem(
                        table,
                        row.id,  # type: ignore[attr-defined]
                        "tampered",
                        f"{_what(row)}: its hash differs from the one audit event {audited[0]} "
                        "recorded at its last"
                        " change (changed outside the daemon and hashed again)",
                    )
                )
    for key, (event_id, _sha) in sorted(left.items()):
        table, _, row_id = key.partition(":")
        report.problems.append(
            Problem(
                table,
                int(row_id) if row_id.isdigit() else None,
                "missing",
                f"audit event {event_id} records this row, but it is gone",
            )
        )


def _verify_samples(session: Session, report: VerifyReport) -> None:
    """Each settled point that holds the hash of its raw samples against the samples stored now."""
    t = SampleRow.__table__
    for settled in session.scalars(
        sa.select(SettledPoint)
        .where(SettledPoint.samples_sha256.is_not(None))
        .order_by(SettledPoint.id)
    ):
        report.sample_points_checked += 1
        rows = session.execute(
            sa.select(*(t.c[name] for name in SAMPLE_FIELDS))
            .where(
                t.c.job_id == settled.job_id,
                t.c.device_id == settled.device_id,
                t.c.point == settled.point,
            )
            .order_by(t.c.t_s, t.c.id)
        ).all()
        if not rows or samples_sha256(rows) != settled.samples_sha256:
            report.problems.append(
                Problem(
                    "samples",
                    None,
                    "raw_data_changed",
                    f"the raw samples of device {settled.device_id} at point {settled.point} of "
                    f"job {settled.job_id} ({len(rows)} stored now) no longer hash to what settled "
                    f"point id={settled.id} recorded: a sample was changed, added or removed",
                )
            )
