"""Issuing and verifying certificates: gathers a record's facts from storage, builds through
`content` and `dcc`, stores the bytes once; verification re-checks a file against the schema,
the stored hash, the record and its approval."""

from __future__ import annotations

import datetime as dt
import hashlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from service import __version__
from service.lims import dcc
from service.lims.as_found import MeasuredPoint
from service.lims.conformity import assess
from service.lims.content import (
    Approval,
    CertificateRefused,
    Laboratory,
    build_certificate,
    found_as,
    parameter_figures,
    standards_of,
)
from service.lims.content_results import parameter_result
from service.storage.canonical import sha256_hex
from service.storage.errors import UnknownEntity
from service.storage.models import CalibrationJob, CalibrationRecord, Certificate, Order
from service.storage.specification import Specification, specification_of
from service.storage.store import Store
from service.storage.store.approvals import signer_of
from service.storage.store.hashing import record_content
from service.storage.tokens import Person

__all__ = [
    "CertificateRefused",
    "IntegrityFailure",
    "NotApproved",
    "NotConfigured",
    "Verification",
    "check_stored",
    "issue_certificate",
    "laboratory",
    "measured_points",
    "record_conformity",
    "signer",
    "verify_certificate",
]

if TYPE_CHECKING:  # the signing libraries are loaded when a certificate is signed
    from service.config import Settings
    from service.lims.signature import Signer


class NotApproved(Exception):
    """A certificate was asked for a record that is a draft or rejected."""


class NotConfigured(Exception):
    """The laboratory's identity, which every certificate names, is not configured."""


class IntegrityFailure(Exception):
    """Stored certificate bytes no longer match their SHA-256 (or the record its hash)."""


def laboratory(settings: Settings) -> Laboratory:
    missing = [
        f"TILTLAB_{n.upper()}"
        for n in ("lab_name", "lab_city", "lab_country_code")
        if not getattr(settings, n)
    ]
    if missing:
        raise NotConfigured(
            f"certificates name the laboratory: set {', '.join(missing)} (see docs/lims.md)"
        )
    return Laboratory(
        name=settings.lab_name,
        city=settings.lab_city,
        country_code=settings.lab_country_code,
        street=settings.lab_street or None,
        post_code=settings.lab_post_code or None,
        email=settings.lab_email or None,
        accreditation=settings.lab_accreditation or None,
        certificate_prefix=settings.certificate_prefix,
    )


def signer(settings: Settings) -> Signer | None:
    """The lab's certificate signer, None when it signs none; NotConfigured when half or wrongly
    configured."""
    key, cert = settings.certificate_signing_key, settings.certificate_signing_cert
    if not key and not cert:
        return None
    if not key or not cert:
        raise NotConfigured(
            "certificates are signed with a key and its certificate: set both "
            "TILTLAB_CERTIFICATE_SIGNING_KEY and TILTLAB_CERTIFICATE_SIGNING_CERT (see "
            "docs/lims.md)"
        )
    from service.lims.signature import SigningNotConfigured, load_signer

    try:
        return load_signer(key, cert)
    except SigningNotConfigured as exc:
        raise NotConfigured(f"certificate signing: {exc}") from None


def _record_json(r: CalibrationRecord) -> dict[str, Any]:
    raw = r.raw_data or {}
    return {
        "id": r.id,
        "version": r.version,
        "kind": r.kind,
        "method": r.method,
        "model": r.model,
        "validation": r.validation,
        "temp_c": r.temp_c,
        "content_sha256": r.content_sha256,
        "created_at": r.created_at,
        "budget": raw.get("budget"),
        "calibrated_range": raw.get("calibrated_range"),
        "conditions": raw.get("conditions") or {},
    }


def _calibration_points(store: Store, r: CalibrationRecord) -> list[dict[str, float]]:
    """Another kind's fit points: the commanded angle at each (the item's indications are in the
    validation)."""
    if r.job_id is None or r.kind == "stage":
        return []
    n_fit = int((r.raw_data or {}).get("fit_points", 10**9))
    points = [
        p
        for p in store.points.settled_points(r.job_id)
        if p.point < n_fit and p.device_id == r.device_id
    ]
    return [
        {"commanded_angle_deg": float(p.cmd_x_deg)}
        for p in sorted(points, key=lambda p: p.point)
        if p.cmd_x_deg is not None
    ]


def measured_points(store: Store, r: CalibrationRecord) -> list[MeasuredPoint]:
    """Every settled point of a stage record's job (calibration and validation), both sensors'
    means, spreads and counts: what the calibration points, the indication errors and statements of
    conformity rest on."""
    if r.job_id is None or r.kind != "stage":
        return []
    n_fit = int((r.raw_data or {}).get("fit_points", 10**9))
    points = store.points.settled_points(r.job_id)
    item = {p.point: p for p in points if p.device_id == r.device_id}
    out = []
    for ref in sorted((p for p in points if p.device_id != r.device_id), key=lambda p: p.point):
        m = item.get(ref.point)
        if m is not None:
            out.append(
                MeasuredPoint(
                    ref.point,
                    ref.point < n_fit,
                    (ref.ch_x_mean, ref.ch_y_mean),
                    (m.ch_x_mean, m.ch_y_mean),
                    (ref.ch_x_std, ref.ch_y_std),
                    (m.ch_x_std, m.ch_y_std),
                    ref.n_samples,
                    m.n_samples,
                )
            )
    return sorted(out, key=lambda p: (not p.fitted, p.point))


def _device_json(store: Store, r: CalibrationRecord) -> dict[str, Any]:
    device = store.devices.get_device(r.device_id)
    conditions = (r.raw_data or {}).get("conditions") or {}
    firmware = conditions.get("firmware")
    if isinstance(firmware, dict):  # per role, as the daemon keeps it
        firmware = firmware.get(device.role) or firmware.get("measurement_sensor")
    return {
        "id": device.id,
        "model": device.model,
        "serial": device.serial,
        "firmware": firmware if isinstance(firmware, str) else None,
    }


def _standards_of(store: Store, r: CalibrationRecord, job: CalibrationJob | None) -> list[Any]:
    """The registered standards the job named (by id), else those the record lists (by certificate
    number)."""
    registered = {s.id: s for s in store.standards.all()}
    ids: list[Any] = []
    if job is not None:
        request = (job.parameters or {}).get("request") or {}
        ids = (
            request.get("reference_standards")
            or (job.parameters or {}).get("reference_standards")
            or []
        )
    out = [registered[int(i)] for i in ids if str(i).isdigit() and int(i) in registered]
    if not out:
        by_number = {s.certificate_number: s for s in registered.values()}
        out = [
            by_number[s["certificate_id"]]
            for s in r.reference_standards or []
            if s.get("certificate_id") in by_number
        ]
    return [
        {
            "name": s.name,
            "serial": s.serial,
            "model": s.model,
            "certificate_number": s.certificate_number,
            "certificate_sha256": s.certificate_sha256,
            "calibrated_on": s.calibrated_on,
            "due_on": s.due_on,
            "uncertainty": s.uncertainty,
            "expanded_uncertainty_deg": s.expanded_uncertainty_deg,
            "coverage_factor": s.coverage_factor,
            "calibrated_by": s.calibrated_by,
        }
        for s in out
    ]


def _operator_person(
    store: Store, r: CalibrationRecord, job: CalibrationJob | None
) -> Person | None:
    """The person behind the token that started the job, as the job kept it when it was started
    (else as the token names it now)."""
    kept = ((job.parameters or {}).get("operator_person") if job is not None else None) or (
        r.raw_data or {}
    ).get("operator_person")
    if isinstance(kept, dict) and kept.get("name"):
        return Person(str(kept["name"]), kept.get("function"))
    return store.tokens.person_of_token(r.operator)


def _performed_on(record: CalibrationRecord, job: CalibrationJob | None) -> dt.date:
    begin = (job.started_at or job.created_at) if job is not None else record.created_at
    return begin.astimezone(dt.UTC).date()


def _specification(order: Order | None) -> Specification | None:
    return (
        specification_of(order.specification) if order is not None and order.specification else None
    )


def record_conformity(store: Store, record: CalibrationRecord) -> dict[str, Any] | None:
    """The statements of conformity the record's order asks for (None without a specification), as
    records, orders and the feed show them: the same figures its certificate states."""
    job = store.jobs.get_job(record.job_id) if record.job_id is not None else None
    order = store.orders.get(job.order_id) if job is not None and job.order_id is not None else None
    spec = _specification(order)
    points = measured_points(store, record)
    if spec is None or not points:
        return None
    facts = _record_json(record)
    named = standards_of(_standards_of(store, record, job), _performed_on(record, job))
    found = found_as(points, named, facts["conditions"])
    params = parameter_figures(parameter_result(record.model, facts["budget"]))
    return assess(spec, found, params).as_json()


def issue_certificate(
    store: Store, record_id: int, settings: Settings, *, actor: str, today: dt.date | None = None
) -> Certificate:
    """The record's certificate: the stored one if it was issued before (after checking its hash),
    else a new one, validated against the DCC schema before it is stored. Raises NotApproved for a
    draft or rejected record, CertificateRefused for one that cannot be certified (not traceable, no
    person authorised it)."""
    existing = store.certificates.certificate_of(record_id)
    if existing is not None:
        check_stored(existing)
        return existing
    record = store.records.get_record(record_id)
    if sha256_hex(record_content(record)) != record.content_sha256:
        raise IntegrityFailure(
            f"record {record_id} does not match its hash (tampered); no certificate is issued"
        )
    approvals = store.approvals.of_record(record_id)
    status = store.approvals.status_of(approvals)
    if status != "approved":
        raise NotApproved(
            f"record {record_id} is {status}; a certificate is issued only for an approved record"
            " (POST /records/{id}/approve by a second person)"
        )
    approval = [a for a in approvals if a.decision == "approve" and a.meaning == "approval"][-1]
    lab = laboratory(settings)
    job = store.jobs.get_job(record.job_id) if record.job_id is not None else None
    order = store.orders.get(job.order_id) if job is not None and job.order_id is not None else None
    replaced = store.certificates.replaced_certificate(record_id)
    today = today or dt.datetime.now(dt.UTC).date()
    spec = _specification(order)
    content = build_certificate(
        number=f"{lab.certificate_prefix}-{today.year}-{record.id:06d}",
        record=_record_json(record),
        device=_device_json(store, record),
        approval=Approval(
            actor=approval.actor,
            at=approval.at,
            meaning=approval.meaning,
            record_sha256=approval.record_sha256,
            event_sha256=approval.sha256,
            note=approval.note,
            signer=signer_of(approval),
        ),
        operator=record.operator,
        operator_person=_operator_person(store, record, job),
        job_id=record.job_id,
        laboratory=lab,
        software_version=__version__,
        issued_on=today,
        begin_on=_performed_on(record, job),
        standards=_standards_of(store, record, job),
        order={
            "lims_order_id": order.lims_order_id,
            "item_serial": order.item_serial,
            "customer": order.customer,
            "item_manufacturer": order.item_manufacturer,
            "item_model": order.item_model,
        }
        if order is not None
        else None,
        calibration_points=_calibration_points(store, record),
        measured_points=measured_points(store, record),
        specification=spec,
        replaces=replaced.number if replaced is not None else None,
    )
    # refuses an invalid document: nothing is stored then
    xml = dcc.issue(content, signer(settings))
    conformity = record_conformity(store, record) if spec is not None else None
    row, _ = store.certificates.store_certificate(
        record_id,
        number=content.number,
        xml=xml,
        approval_id=approval.id,
        replaces_id=replaced.id if replaced is not None else None,
        actor=actor,
        conformity=conformity,
    )
    check_stored(row)
    return row


def check_stored(cert: Certificate) -> None:
    if hashlib.sha256(cert.xml).hexdigest() != cert.sha256:
        raise IntegrityFailure(
            f"stored certificate {cert.number} no longer matches its SHA-256 {cert.sha256};"
            " it is not served (restore it from a backup; it is never regenerated)"
        )


@dataclass
class Verification:
    number: str = ""
    sha256: str = ""
    problems: list[str] = field(default_factory=list)
    facts: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def verify_certificate(
    xml: bytes,
    store: Store | None = None,
    trusted_cert_pem: bytes | None = None,
    *,
    allow_unsigned: bool = False,
) -> Verification:
    """Schema validity and the enveloped signature (offline; with `trusted_cert_pem` the signer must
    be that certificate), and with a store: the stored hash, the record's hash and the approval it
    rests on.

    A file without a signature fails (its signature may have been stripped) unless `allow_unsigned`,
    or unless the laboratory's database holds it byte for byte (a laboratory that does not sign its
    certificates)."""
    v = Verification(sha256=hashlib.sha256(xml).hexdigest())
    errors = dcc.certificate_errors(xml)
    if errors:
        v.problems.append(f"not a valid DCC {dcc.DCC_VERSION} document: {errors[0]}")
        return v
    v.facts.append(
        f"valid DCC {dcc.DCC_VERSION} document (checked offline against the shipped schemas)"
    )
    v.number = dcc.unique_identifier(xml)
    from service.lims import signature  # signxml and lxml load only when a certificate is checked

    sig = signature.check(xml, trusted_cert_pem)
    unsigned = not sig.signed and trusted_cert_pem is None
    if sig.ok:
        v.facts.append(
            f"{sig.detail}; signed by {sig.signer} (certificate SHA-256 {sig.cert_sha256})"
            + (", the certificate given" if trusted_cert_pem else "")
        )
    elif not unsigned:
        v.problems.append(f"signature: {sig.detail}")
    elif allow_unsigned:
        v.facts.append(
            "not signed, accepted as asked (--allow-unsigned): nothing in the file shows "
            "whether it was altered"
        )
    elif store is None:
        v.problems.append(
            "not signed: the file carries no signature, so nothing shows it is unaltered (a "
            "signature may have been stripped); check it against the laboratory's database "
            "(without --offline), or accept an unsigned file with --allow-unsigned"
        )
    if store is None:
        return v
    stored = store.certificates.certificate_by_number(v.number)
    if stored is None:
        v.problems.append(f"certificate {v.number} was not issued by this laboratory's database")
        return v
    if hashlib.sha256(stored.xml).hexdigest() != stored.sha256:
        v.problems.append(
            f"the stored copy of {v.number} no longer matches its SHA-256 (the database was "
            "altered)"
        )
    if v.sha256 != stored.sha256:
        v.problems.append(
            f"this file's SHA-256 {v.sha256} differs from the one stored at issue {stored.sha256}:"
            " the file was altered"
            + (" (its signature may have been stripped)" if unsigned else "")
        )
    else:
        v.facts.append(
            f"SHA-256 {v.sha256} equals the one stored when it was issued"
            + (" (the laboratory issued it unsigned)" if unsigned else "")
        )
    try:
        record = store.records.get_record(stored.record_id)
    except UnknownEntity:
        v.problems.append(f"record {stored.record_id} of {v.number} is missing")
        return v
    if sha256_hex(record_content(record)) != record.content_sha256:
        v.problems.append(f"record {record.id} no longer matches its hash (tampered)")
    approvals = {a.id: a for a in store.approvals.of_record(record.id)}
    approval = approvals.get(stored.approval_id)
    if approval is None or approval.record_sha256 != record.content_sha256:
        v.problems.append(f"the approval of record {record.id} is missing or bound to another hash")
    else:
        person = signer_of(approval)
        v.facts.append(
            f"record {record.id} v{record.version} (SHA-256 {record.content_sha256}) approved by "
            + (f"{person.described()} (token {approval.actor})" if person else approval.actor)
            + f" at {approval.at:%Y-%m-%d %H:%M:%S} UTC ({approval.meaning})"
        )
    v.problems += store.approvals.verify_approvals()
    return v
