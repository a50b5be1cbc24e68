"""Integrity check of calibration records and the audit log, from the database alone.

A record or event whose content does not hash to its stored SHA-256 is *tampered*; one whose
predecessor hash does not match the stored hash of the row before it (or whose predecessor is
missing) is a *broken chain*. Record creations are also cross-checked with their audit events,
which catches the removal of the newest version of a chain; so are approvals and rejections, which
catches the removal of the newest decision (the approvals' own chain cannot see its end). A
record made by a job is checked against the settled points of every device of that job (the
reference sensor's included: the fit used them). The newest audit event can only be
vouched for against a copy of its hash kept elsewhere: the report prints it for that purpose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import sqlalchemy as sa
from sqlalchemy.orm import Session

from service.storage.canonical import sha256_hex
from service.storage.models import GENESIS_SHA256, AuditEvent, CalibrationRecord, SettledPoint
from service.storage.store.hashing import audit_content, points_sha256, record_content


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
    audit_head_sha256: str = GENESIS_SHA256
    problems: list[Problem] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    @property
    def tampered(self) -> list[Problem]:
        return [p for p in self.problems if p.kind == "tampered"]

    @property
    def broken(self) -> list[Problem]:
        return [p for p in self.problems if p.kind != "tampered"]

    def lines(self) -> list[str]:
        out = [
            f"calibration records checked: {self.records_checked}",
            f"audit events checked: {self.audit_events_checked}",
            f"approvals and rejections checked: {self.approvals_checked}",
            f"audit head sha256: {self.audit_head_sha256}",
        ]
        out += [str(p) for p in self.problems]
        out.append("OK: every hash and chain link verifies" if self.ok else f"FAILED: {len(self.problems)} problem(s)")
        return out


def verify(engine: sa.Engine) -> VerifyReport:
    report = VerifyReport()
    with Session(engine) as s:
        _verify_records(s, report)
        created, decided = _verify_audit(s, report)
        _cross_check(s, report, created)
        _verify_approvals_and_certificates(s, report, decided)
    return report


def _verify_records(s: Session, report: VerifyReport) -> None:
    records = s.scalars(
        sa.select(CalibrationRecord).order_by(CalibrationRecord.device_id, CalibrationRecord.kind, CalibrationRecord.version)
    )
    prev: CalibrationRecord | None = None
    for r in records:
        report.records_checked += 1
        if sha256_hex(record_content(r)) != r.content_sha256:
            report.problems.append(Problem("calibration_records", r.id, "tampered",
                f"device {r.device_id} {r.kind} v{r.version}: content does not match its SHA-256"))  # fmt: skip
        same_chain = prev is not None and (prev.device_id, prev.kind) == (r.device_id, r.kind)
        expected_version = prev.version + 1 if same_chain else 1  # type: ignore[union-attr]
        expected_prev = prev.content_sha256 if same_chain else GENESIS_SHA256  # type: ignore[union-attr]
        if r.version != expected_version:
            report.problems.append(Problem("calibration_records", r.id, "broken_chain",
                f"device {r.device_id} {r.kind}: v{r.version} follows v{expected_version - 1}; a version is missing"))  # fmt: skip
        elif r.prev_sha256 != expected_prev:
            report.problems.append(Problem("calibration_records", r.id, "broken_chain",
                f"device {r.device_id} {r.kind} v{r.version}: predecessor hash does not match v{r.version - 1}"))  # fmt: skip
        if r.job_id is not None:
            _verify_points(s, report, r)
        prev = r


def _verify_points(s: Session, report: VerifyReport, r: CalibrationRecord) -> None:
    """The job's settled points against the hashes the record holds: every device's (records made since the
    per-device hashes exist), else the record's own device's (older records: all they committed to)."""
    by_device = r.raw_data.get("settled_points_sha256")
    if not isinstance(by_device, dict):
        by_device = {str(r.device_id): r.raw_data["points_sha256"]} if "points_sha256" in r.raw_data else {}
    stored: dict[str, list[SettledPoint]] = {}
    for p in s.scalars(sa.select(SettledPoint).where(SettledPoint.job_id == r.job_id)):
        stored.setdefault(str(p.device_id), []).append(p)
    for device, sha in sorted(by_device.items()):
        if points_sha256(stored.get(device, [])) != sha:
            report.problems.append(Problem("calibration_records", r.id, "raw_data_changed",
                f"the settled points of device {device} in job {r.job_id} no longer hash to what v{r.version}"
                " was fitted on"))  # fmt: skip
    if "settled_points_sha256" in r.raw_data:
        for device in sorted(set(stored) - set(by_device)):
            report.problems.append(Problem("calibration_records", r.id, "raw_data_changed",
                f"job {r.job_id} has settled points of device {device} that v{r.version} did not record"))  # fmt: skip


_DECISIONS = ("record.approve", "record.review", "record.reject")


def _verify_audit(s: Session, report: VerifyReport) -> tuple[dict[int, str], dict[int, tuple[int, str]]]:
    """Walks the chain in id order; returns record id -> content hash from record.create events, and
    approval id -> (audit event id, approval hash) from the decisions' events."""
    created: dict[int, str] = {}
    decided: dict[int, tuple[int, str]] = {}
    prev_sha = GENESIS_SHA256
    for e in s.scalars(sa.select(AuditEvent).order_by(AuditEvent.id)).yield_per(1000):
        report.audit_events_checked += 1
        if sha256_hex(audit_content(e)) != e.sha256:
            report.problems.append(Problem("audit_events", e.id, "tampered",
                f"{e.action} by {e.actor} at {e.at:%Y-%m-%d %H:%M:%S}: content does not match its SHA-256"))  # fmt: skip
        if e.prev_sha256 != prev_sha:
            report.problems.append(Problem("audit_events", e.id, "broken_chain",
                "predecessor hash does not match the previous event; an event was removed or altered"))  # fmt: skip
        if e.action == "record.create":
            created[int(e.entity_id)] = str(e.details.get("content_sha256"))
        elif e.action in _DECISIONS and isinstance(e.details.get("approval_id"), int):
            decided[e.details["approval_id"]] = (e.id, str(e.details.get("approval_sha256")))
        prev_sha = e.sha256
    report.audit_head_sha256 = prev_sha
    return created, decided


def _cross_check(s: Session, report: VerifyReport, created: dict[int, str]) -> None:
    stored = {rid: sha for rid, sha in s.execute(sa.select(CalibrationRecord.id, CalibrationRecord.content_sha256))}
    for record_id, sha in sorted(created.items()):
        if record_id not in stored:
            report.problems.append(Problem("calibration_records", record_id, "missing",
                "the audit log records its creation but the record is gone"))  # fmt: skip
        elif stored[record_id] != sha:
            report.problems.append(Problem("calibration_records", record_id, "tampered",
                "its hash differs from the one recorded in the audit log at creation"))  # fmt: skip
    for record_id in sorted(set(stored) - set(created)):
        report.problems.append(Problem("calibration_records", record_id, "missing",
            "no audit event records its creation"))  # fmt: skip


def _verify_approvals_and_certificates(s: Session, report: VerifyReport, decided: dict[int, tuple[int, str]]) -> None:
    """Approvals: content against hash, the chain, and each against the audit event of its decision (the
    audit chain anchors the approvals' newest end); issued certificates: stored bytes against their SHA-256."""
    import hashlib

    from service.storage.canonical import normalise
    from service.storage.models import Certificate, RecordApproval
    from service.storage.store.approvals import approval_content

    prev = GENESIS_SHA256
    for a in s.scalars(sa.select(RecordApproval).order_by(RecordApproval.id)):
        if sha256_hex(normalise(approval_content(a))) != a.sha256:
            report.problems.append(Problem("record_approvals", a.id, "tampered",
                f"{a.decision} of record {a.record_id} by {a.actor}: content does not match its SHA-256"))  # fmt: skip
        if a.prev_sha256 != prev:
            report.problems.append(Problem("record_approvals", a.id, "broken_chain",
                "predecessor hash does not match the previous approval; one was removed or altered"))  # fmt: skip
        audited = decided.pop(a.id, None)
        if audited is None:
            report.problems.append(Problem("record_approvals", a.id, "missing",
                f"no audit event records the {a.decision} of record {a.record_id} by {a.actor}"))  # fmt: skip
        elif audited[1] != a.sha256:
            report.problems.append(Problem("record_approvals", a.id, "tampered",
                f"its hash differs from the one audit event {audited[0]} recorded at the decision"))  # fmt: skip
        report.approvals_checked += 1
        prev = a.sha256
    for approval_id, (event_id, _sha) in sorted(decided.items()):
        event = s.get(AuditEvent, event_id)
        what = f"{event.action} of record {event.entity_id} by {event.actor}" if event is not None else "a decision"
        report.problems.append(Problem("record_approvals", approval_id, "missing",
            f"audit event {event_id} records {what} but the approval is gone (a record's status would read"
            " as if that decision was never made)"))  # fmt: skip
    for c in s.scalars(sa.select(Certificate).order_by(Certificate.id)):
        if hashlib.sha256(c.xml).hexdigest() != c.sha256:
            report.problems.append(Problem("certificates", c.id, "tampered",
                f"certificate {c.number}: stored bytes do not match the SHA-256 recorded at issue"))  # fmt: skip
