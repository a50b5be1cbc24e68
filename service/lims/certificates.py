"""Issuing and verifying certificates: gathers a record's facts from storage, builds through
`content` and `dcc`, stores the bytes once; verification re-checks a file against the schema,
the stored hash, the record and its approval."""

from __future__ import annotations

import datetime as dt
import hashlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, cast

from service import __version__
from service.lims import dcc
from service.lims.as_found import MeasuredPoint
from service.lims.conformity import ConformityJson, assess
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
from service.lims.facts import (
    CalibratingLab,
    CustomerFacts,
    DeviceFacts,
    ModelDocument,
    OrderFacts,
    RecordConditions,
    RecordFacts,
    StandardFacts,
    Validation,
)
from service.storage.canonical import sha256_hex
from service.storage.errors import UnknownEntity
from service.storage.models import (
    CalibrationJob,
    CalibrationRecord,
    Certificate,
    Order,
    RecordApproval,
    ReferenceStandard,
)
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
        f"TILTLAB_{setting.upper()}"
        for setting in ("lab_name", "lab_city", "lab_country_code")
        if not getattr(settings, setting)
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


def _record_json(r: CalibrationRecord) -> RecordFacts:
    """The record as the certificate's content reads it; its JSON columns as stored (MODEL.json,
    the validation, the raw data's budget, range and conditions)."""
    raw = r.raw_data or {}
    return {
        "id": r.id,
        "version": r.version,
        "kind": r.kind,
        "method": r.method,
        "model": cast(ModelDocument, r.model),
        "validation": cast(Validation, r.validation),
        "temp_c": r.temp_c,
        "content_sha256": r.content_sha256,
        "created_at": r.created_at,
        "budget": raw.get("budget"),
        "calibrated_range": raw.get("calibrated_range"),
        "conditions": cast(RecordConditions, raw.get("conditions") or {}),
    }


def _calibration_points(store: Store, r: CalibrationRecord) -> list[dict[str, float]]:
    """Another kind's fit points: the commanded angle at each (the item's indications are in the
    validation)."""
    if r.job_id is None or r.kind == "stage":
        return []
    n_fit = int((r.raw_data or {}).get("fit_points", 10**9))
    points = [
        point
        for point in store.points.settled_points(r.job_id)
        if point.point < n_fit and point.device_id == r.device_id
    ]
    return [
        {"commanded_angle_deg": float(point.cmd_x_deg)}
        for point in sorted(points, key=lambda point: point.point)
        if point.cmd_x_deg is not None
    ]


def measured_points(store: Store, r: CalibrationRecord) -> list[MeasuredPoint]:
    """Every settled point of a stage record's job (calibration and validation), both sensors'
    means, spreads and counts: what the calibration points, the indication errors and statements of
    conformity rest on."""
    if r.job_id is None or r.kind != "stage":
        return []
    n_fit = int((r.raw_data or {}).get("fit_points", 10**9))
    points = store.points.settled_points(r.job_id)
    item = {point.point: point for point in points if point.device_id == r.device_id}
    out = []
    for ref in sorted(
        (point for point in points if point.device_id != r.device_id),
        key=lambda point: point.point,
    ):
        indicated = item.get(ref.point)
        if indicated is not None:
            out.append(
                MeasuredPoint(
                    ref.point,
                    ref.point < n_fit,
                    (ref.ch_x_mean, ref.ch_y_mean),
                    (indicated.ch_x_mean, indicated.ch_y_mean),
                    (ref.ch_x_std, ref.ch_y_std),
                    (indicated.ch_x_std, indicated.ch_y_std),
                    ref.n_samples,
                    indicated.n_samples,
                )
            )
    return sorted(out, key=lambda point: (not point.fitted, point.point))


def _device_json(store: Store, r: CalibrationRecord) -> DeviceFacts:
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


def _requested_standard_ids(job: CalibrationJob | None) -> list[object]:
    """The standards the job's request named by id (older jobs kept them beside the request)."""
    if job is None:
        return []
    request = (job.parameters or {}).get("request") or {}
    ids: list[object] = (
        request.get("reference_standards")
        or (job.parameters or {}).get("reference_standards")
        or []
    )
    return ids


def _standard_json(standard: ReferenceStandard) -> StandardFacts:
    """A registered standard as the certificate's content reads it."""
    return {
        "name": standard.name,
        "serial": standard.serial,
        "model": standard.model,
        "certificate_number": standard.certificate_number,
        "certificate_sha256": standard.certificate_sha256,
        "calibrated_on": standard.calibrated_on,
        "due_on": standard.due_on,
        "uncertainty": standard.uncertainty,
        "expanded_uncertainty_deg": standard.expanded_uncertainty_deg,
        "coverage_factor": standard.coverage_factor,
        "calibrated_by": cast(CalibratingLab | None, standard.calibrated_by),
    }


def _listed_standards(
    registered: dict[int, ReferenceStandard], r: CalibrationRecord
) -> list[ReferenceStandard]:
    """The registered standards whose certificate numbers the record lists (when the job named none
    by id)."""
    by_number = {standard.certificate_number: standard for standard in registered.values()}
    return [
        by_number[listed["certificate_id"]]
        for listed in r.reference_standards or []
        if listed.get("certificate_id") in by_number
    ]


def _standards_of(
    store: Store, r: CalibrationRecord, job: CalibrationJob | None
) -> list[StandardFacts]:
    """The registered standards the job named (by id), else those the record lists (by certificate
    number)."""
    registered = {standard.id: standard for standard in store.standards.all()}
    named = [int(str(i)) for i in _requested_standard_ids(job) if str(i).isdigit()]
    out = [registered[i] for i in named if i in registered]
    if not out:
        out = _listed_standards(registered, r)
    return [_standard_json(standard) for standard in out]


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


def _job_and_order(
    store: Store, record: CalibrationRecord
) -> tuple[CalibrationJob | None, Order | None]:
    """The job that made the record and the order it ran for, each None where there is none."""
    job = store.jobs.get_job(record.job_id) if record.job_id is not None else None
    order = store.orders.get(job.order_id) if job is not None and job.order_id is not None else None
    return job, order


def record_conformity(store: Store, record: CalibrationRecord) -> ConformityJson | None:
    """The statements of conformity the record's order asks for (None without a specification), as
    records, orders and the feed show them: the same figures its certificate states."""
    job, order = _job_and_order(store, record)
    spec = _specification(order)
    points = measured_points(store, record)
    if spec is None or not points:
        return None
    facts = _record_json(record)
    named = standards_of(_standards_of(store, record, job), _performed_on(record, job))
    found = found_as(points, named, facts["conditions"])
    params = parameter_figures(parameter_result(facts["model"], facts["budget"]))
    return assess(spec, found, params).as_json()


def _approval_of(store: Store, record_id: int) -> RecordApproval:
    """The approval a certificate rests on (the last one); NotApproved for a draft or rejected
    record."""
    approvals = store.approvals.of_record(record_id)
    status = store.approvals.status_of(approvals)
    if status != "approved":
        raise NotApproved(
            f"record {record_id} is {status}; a certificate is issued only for an approved record"
            " (POST /records/{id}/approve by a second person)"
        )
    return [
        event for event in approvals if event.decision == "approve" and event.meaning == "approval"
    ][-1]


def _approval_content(approval: RecordApproval) -> Approval:
    """The stored approval event as the certificate's content names it."""
    return Approval(
        actor=approval.actor,
        at=approval.at,
        meaning=approval.meaning,
        record_sha256=approval.record_sha256,
        event_sha256=approval.sha256,
        note=approval.note,
        signer=signer_of(approval),
    )


def _order_json(order: Order | None) -> OrderFacts | None:
    """What the certificate's content reads of the order, None for an in-house calibration."""
    if order is None:
        return None
    return {
        "lims_order_id": order.lims_order_id,
        "item_serial": order.item_serial,
        "customer": cast(CustomerFacts, order.customer),
        "item_manufacturer": order.item_manufacturer,
        "item_model": order.item_model,
    }


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
    approval = _approval_of(store, record_id)
    lab = laboratory(settings)
    job, order = _job_and_order(store, record)
    replaced = store.certificates.replaced_certificate(record_id)
    today = today or dt.datetime.now(dt.UTC).date()
    spec = _specification(order)
    content = build_certificate(
        number=f"{lab.certificate_prefix}-{today.year}-{record.id:06d}",
        record=_record_json(record),
        device=_device_json(store, record),
        approval=_approval_content(approval),
        operator=record.operator,
        operator_person=_operator_person(store, record, job),
        job_id=record.job_id,
        laboratory=lab,
        software_version=__version__,
        issued_on=today,
        begin_on=_performed_on(record, job),
        standards=_standards_of(store, record, job),
        order=_order_json(order),
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


def _check_signature(
    verification: Verification,
    xml: bytes,
    store: Store | None,
    trusted_cert_pem: bytes | None,
    allow_unsigned: bool,
) -> bool:
    """Checks the enveloped signature into the verification; True when the file is unsigned and no
    certificate was given to check it with."""
    from service.lims import signature  # signxml and lxml load only when a certificate is checked

    sig = signature.check(xml, trusted_cert_pem)
    unsigned = not sig.signed and trusted_cert_pem is None
    if sig.ok:
        verification.facts.append(
            f"{sig.detail}; signed by {sig.signer} (certificate SHA-256 {sig.cert_sha256})"
            + (", the certificate given" if trusted_cert_pem else "")
        )
    elif not unsigned:
        verification.problems.append(f"signature: {sig.detail}")
    elif allow_unsigned:
        verification.facts.append(
            "not signed, accepted as asked (--allow-unsigned): nothing in the file shows "
            "whether it was altered"
        )
    elif store is None:
        verification.problems.append(
            "not signed: the file carries no signature, so nothing shows it is unaltered (a "
            "signature may have been stripped); check it against the laboratory's database "
            "(without --offline), or accept an unsigned file with --allow-unsigned"
        )
    return unsigned


def _check_stored_copy(verification: Verification, stored: Certificate, unsigned: bool) -> None:
    """The stored copy still matches its hash, and the file matches the stored copy."""
    if hashlib.sha256(stored.xml).hexdigest() != stored.sha256:
        verification.problems.append(
            f"the stored copy of {verification.number} no longer matches its SHA-256 (the "
            "database was altered)"
        )
    if verification.sha256 != stored.sha256:
        verification.problems.append(
            f"this file's SHA-256 {verification.sha256} differs from the one stored at issue "
            f"{stored.sha256}: the file was altered"
            + (" (its signature may have been stripped)" if unsigned else "")
        )
    else:
        verification.facts.append(
            f"SHA-256 {verification.sha256} equals the one stored when it was issued"
            + (" (the laboratory issued it unsigned)" if unsigned else "")
        )


def _check_record(verification: Verification, store: Store, stored: Certificate) -> None:
    """The record the certificate states still matches its hash, and its approval is bound to
    it."""
    try:
        record = store.records.get_record(stored.record_id)
    except UnknownEntity:
        verification.problems.append(
            f"record {stored.record_id} of {verification.number} is missing"
        )
        return
    if sha256_hex(record_content(record)) != record.content_sha256:
        verification.problems.append(f"record {record.id} no longer matches its hash (tampered)")
    approvals = {event.id: event for event in store.approvals.of_record(record.id)}
    approval = approvals.get(stored.approval_id)
    if approval is None or approval.record_sha256 != record.content_sha256:
        verification.problems.append(
            f"the approval of record {record.id} is missing or bound to another hash"
        )
    else:
        person = signer_of(approval)
        verification.facts.append(
            f"record {record.id} v{record.version} (SHA-256 {record.content_sha256}) approved by "
            + (f"{person.described()} (token {approval.actor})" if person else approval.actor)
            + f" at {approval.at:%Y-%m-%d %H:%M:%S} UTC ({approval.meaning})"
        )
    verification.problems += store.approvals.verify_approvals()


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
    verification = Verification(sha256=hashlib.sha256(xml).hexdigest())
    errors = dcc.certificate_errors(xml)
    if errors:
        verification.problems.append(f"not a valid DCC {dcc.DCC_VERSION} document: {errors[0]}")
        return verification
    verification.facts.append(
        f"valid DCC {dcc.DCC_VERSION} document (checked offline against the shipped schemas)"
    )
    verification.number = dcc.unique_identifier(xml)
    unsigned = _check_signature(verification, xml, store, trusted_cert_pem, allow_unsigned)
    if store is None:
        return verification
    stored = store.certificates.certificate_by_number(verification.number)
    if stored is None:
        verification.problems.append(
            f"certificate {verification.number} was not issued by this laboratory's database"
        )
        return verification
    _check_stored_copy(verification, stored, unsigned)
    _check_record(verification, store, stored)
    return verification
