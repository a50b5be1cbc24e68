"""Integrity check of calibration records and the audit log, from the database alone.

A record or event whose content does not hash to its stored SHA-256 is *tampered*; one whose
predecessor hash does not match the stored hash of the row before it (or whose predecessor is
missing) is a *broken chain*. Record creations are also cross-checked with their audit events,
which catches the removal of the newest version of a chain. The newest audit event can only be
vouched for against a copy of its hash kept elsewhere: the report prints it for that purpose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import sqlalchemy as sa
from sqlalchemy.orm import Session

from service.storage.canonical import sha256_hex
from service.storage.models import GENESIS_SHA256, AuditEvent, CalibrationRecord, SettledPoint
from service.storage.store import audit_content, points_sha256, record_content


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
            f"audit head sha256: {self.audit_head_sha256}",
        ]
        out += [str(p) for p in self.problems]
        out.append("OK: every hash and chain link verifies" if self.ok else f"FAILED: {len(self.problems)} problem(s)")
        return out


def verify(engine: sa.Engine) -> VerifyReport:
    report = VerifyReport()
    with Session(engine) as s:
        _verify_records(s, report)
        created = _verify_audit(s, report)
        _cross_check(s, report, created)
        _verify_approvals_and_certificates(s, report)
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
        if r.job_id is not None and "points_sha256" in r.raw_data:
            pts = list(s.scalars(sa.select(SettledPoint).where(
                SettledPoint.job_id == r.job_id, SettledPoint.device_id == r.device_id)))  # fmt: skip
            if points_sha256(pts) != r.raw_data["points_sha256"]:
                report.problems.append(Problem("calibration_records", r.id, "raw_data_changed",
                    f"the settled points of job {r.job_id} no longer hash to what v{r.version} was fitted on"))  # fmt: skip
        prev = r


def _verify_audit(s: Session, report: VerifyReport) -> dict[int, str]:
    """Walks the chain in id order; returns record id -> content hash from record.create events."""
    created: dict[int, str] = {}
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
        prev_sha = e.sha256
    report.audit_head_sha256 = prev_sha
    return created


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


def _verify_approvals_and_certificates(s: Session, report: VerifyReport) -> None:
    """Approvals: content against hash and the chain; issued certificates: stored bytes against their SHA-256."""
    import hashlib

    from service.storage.canonical import normalise
    from service.storage.lims import approval_content
    from service.storage.models import Certificate, RecordApproval

    prev = GENESIS_SHA256
    for a in s.scalars(sa.select(RecordApproval).order_by(RecordApproval.id)):
        if sha256_hex(normalise(approval_content(a))) != a.sha256:
            report.problems.append(Problem("record_approvals", a.id, "tampered",
                f"{a.decision} of record {a.record_id} by {a.actor}: content does not match its SHA-256"))  # fmt: skip
        if a.prev_sha256 != prev:
            report.problems.append(Problem("record_approvals", a.id, "broken_chain",
                "predecessor hash does not match the previous approval; one was removed or altered"))  # fmt: skip
        prev = a.sha256
    for c in s.scalars(sa.select(Certificate).order_by(Certificate.id)):
        if hashlib.sha256(c.xml).hexdigest() != c.sha256:
            report.problems.append(Problem("certificates", c.id, "tampered",
                f"certificate {c.number}: stored bytes do not match the SHA-256 recorded at issue"))  # fmt: skip
