"""What a certificate says about one approved calibration record, in the lab's words.

Pure: maps a record (as the API shows it: method, MODEL.json, validation, conditions), the device,
the approval, the order and the reference standards to a `dcc.Certificate`. Storage and the API
gather those facts; nothing here reads them.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from service.calibration.budget import model_dof
from service.calibration.uncertainty import COVERAGE, coverage_factor
from service.lims import dcc

# The papers each kind of calibration follows, and the procedure name the daemon runs it under.
PAPERS: dict[str, tuple[str, str]] = {
    "stage": (
        ("Wang S., Chang Y., Cui Y., Liu B.: Error correction for off-axis tilt measurement using biaxial tilt "
        "sensor. Journal of Electronic Measurement and Instrumentation, doi:10.13382/j.jemi.B2407429"),
        "stage-grid",
    ),
    "rotation": (
        ("Cao J., Zhu X., Wu H., Zhang L.: An improved method for measurement of omni-directional spatial "
        "rotation angles (IODSRA), 2016"),
        "rotation",
    ),
    "scale": (
        ("Zhong Q., Tan L., Huang X., Wang L., Wang J.: Demarcating measuring unit of pedestal obliquity "
        "measuring system of gyroscope based on least squares method, doi:10.3969/j.issn.1006-1576.2012.12.019"),
        "scale",
    ),
    "turntable": (
        "Liu X., Zhou Z., Zhang Z., Liu D., Zhu W.: Calibration of inclinometer parameters in digital zenith camera",
        "turntable",
    ),
}
KIND_TEXT = {
    "stage": "biaxial inclinometer on a two-axis tilt stage, against a reference inclinometer",
    "rotation": "triaxial inclinometer module on a rotary bench (spatial rotation angles)",
    "scale": "ADC inclinometer channel against the stage and the reference inclinometer (measuring unit)",
    "turntable": "RS-485 inclinometer on a turntable at symmetric azimuths (scale factors and axis angle)",
}


class CertificateRefused(ValueError):
    """The record cannot be certified as it stands (the message says what is missing)."""


@dataclass(frozen=True)
class Laboratory:
    name: str
    city: str
    country_code: str
    street: str | None = None
    post_code: str | None = None
    email: str | None = None
    accreditation: str | None = None
    certificate_prefix: str = "TL"

    def contact(self) -> dcc.Contact:
        return dcc.Contact(self.name, dcc.Address(self.city, self.country_code, self.street, self.post_code), self.email)


@dataclass(frozen=True)
class Approval:
    """The approval event a certificate rests on (who, when, what it means, and the hash it was bound to)."""

    actor: str
    at: dt.datetime
    meaning: str
    record_sha256: str
    event_sha256: str
    note: str = ""


def parameter_values(model: Mapping[str, Any], probability: float = COVERAGE) -> tuple[dcc.Value, ...]:
    """Every parameter with its expanded uncertainty U = k·u (u from the covariance's diagonal)."""
    params = model.get("parameters") or {}
    cov = model.get("covariance") or None
    std: dict[str, float] = {}
    if cov:
        matrix = np.asarray(cov["matrix"], dtype=float)
        std = {n: math.sqrt(max(float(matrix[i, i]), 0.0)) for i, n in enumerate(cov["names"])}
    k = float(coverage_factor(model_dof(model), probability))
    out = []
    for name, p in params.items():
        note = str(p.get("note") or "")
        if p.get("fixed"):
            out.append(dcc.Value(name, f"{name} (held fixed, not fitted)", float(p["value"]), str(p["unit"]), note=note))
        elif name in std:
            out.append(dcc.Value(name, name, float(p["value"]), str(p["unit"]), std[name] * k, k, probability, note))
        else:
            out.append(dcc.Value(name, name, float(p["value"]), str(p["unit"]), note=note))
    if not out:
        raise CertificateRefused("the record's model has no parameters")
    return tuple(out)


def _quantities(points: Sequence[Mapping[str, Any]]) -> list[tuple[str, str]]:
    """(quantity, unit) pairs that every validation point gives as reference_<q>_<unit> and measured_<q>_<unit>."""
    first = points[0]
    out = []
    for key in first:
        if key.startswith("reference_"):
            rest = key.removeprefix("reference_")
            q, _, unit = rest.rpartition("_")
            if q and f"measured_{rest}" in first:
                out.append((q, unit))
    return out


def validation_result(validation: Mapping[str, Any], probability: float = COVERAGE,
                      k_bound: float | None = None) -> dcc.Result | None:
    """The validation table (reference, measured, error, each error's expanded uncertainty) and its summary.

    Reads `validation["points"]`: one row per validation point with `reference_<q>_<unit>`,
    `measured_<q>_<unit>`, optionally `u_<q>_<unit>` (expanded uncertainty of the measured value)
    and `k_<q>` or `k` (its coverage factor). The error is measured − reference.
    """
    summary = []
    for key, name in (("rms_deg", "RMS of the errors"), ("max_deg", "largest |error|")):
        if isinstance(validation.get(key), int | float):
            summary.append(dcc.Value(key, name, float(validation[key]), "deg"))
    points = validation.get("points") or []
    if isinstance(validation.get("coverage_probability"), int | float):
        probability = float(validation["coverage_probability"])
    if isinstance(validation.get("n_points"), int):
        summary.append(dcc.Value("n_points", "validation points", float(validation["n_points"]), "1"))
    columns: list[dcc.Column] = []
    if points:
        quantities = _quantities(points)
        if not quantities:
            raise CertificateRefused("validation points name no reference_<quantity>_<unit>/measured_... pair")
        for q, unit in quantities:
            ref = tuple(float(p[f"reference_{q}_{unit}"]) for p in points)
            meas = tuple(float(p[f"measured_{q}_{unit}"]) for p in points)
            err = tuple(m - r for m, r in zip(meas, ref, strict=True))
            ukey = f"u_{q}_{unit}"
            has_u = all(isinstance(p.get(ukey), int | float) for p in points)
            U = tuple(float(p[ukey]) for p in points) if has_u else None
            stated = [p.get(f"k_{q}", p.get("k", validation.get("k"))) for p in points]
            if has_u and any(k is None for k in stated) and k_bound is None:
                raise CertificateRefused(f"validation points give {ukey} without its coverage factor")
            # a missing k falls back to the bound, which the refusal above guarantees is there
            ks = tuple(float(k) if k is not None else float(cast(float, k_bound)) for k in stated) if has_u else None
            columns += [
                dcc.Column(f"reference_{q}_{unit}", f"reference {q}", ref, unit, ref_type="basic_referenceValue"),
                dcc.Column(f"measured_{q}_{unit}", f"measured {q} (corrected)", meas, unit, U, ks,
                           probability if has_u else None, ref_type="basic_measuredValue"),
                dcc.Column(f"error_{q}_{unit}", f"error {q} (measured − reference)", err, unit, U, ks,
                           probability if has_u else None, ref_type="basic_measurementError"),
            ]  # fmt: skip
    if not summary and not columns:
        return None
    return dcc.Result(
        "Validation on points not used in the fit",
        "Each validation point was measured after the fit and corrected with the fitted parameters; the error "
        "is the corrected reading minus the reference. The uncertainty of the error is that of the corrected "
        "reading (GUM propagation of the parameters' covariance and the reading noise)"
        + ("; where a point does not state its own coverage factor (Welch-Satterthwaite), the one shown is Student's "
           "t at the fit's degrees of freedom, an upper bound of it, and U covers the stated probability." if k_bound
           else "."),
        values=tuple(summary), columns=tuple(columns),
    )


def _date(value: Any) -> dt.date:
    if isinstance(value, dt.datetime):
        return value.astimezone(dt.UTC).date()
    if isinstance(value, dt.date):
        return value
    return dt.date.fromisoformat(str(value)[:10])


def standards_of(rows: Iterable[Mapping[str, Any]]) -> tuple[dcc.ReferenceStandard, ...]:
    return tuple(
        dcc.ReferenceStandard(
            name=str(s["name"]), serial=str(s["serial"]), certificate_number=str(s["certificate_number"]),
            certificate_sha256=str(s["certificate_sha256"]), calibrated_on=_date(s["calibrated_on"]),
            due_on=_date(s["due_on"]), uncertainty=str(s["uncertainty"]), model=s.get("model") or None,
        )
        for s in rows
    )  # fmt: skip


def build_certificate(
    *,
    number: str,
    record: Mapping[str, Any],
    device: Mapping[str, Any],
    approval: Approval,
    operator: str,
    laboratory: Laboratory,
    software_version: str,
    issued_on: dt.date,
    begin_on: dt.date,
    standards: Sequence[Mapping[str, Any]] = (),
    order: Mapping[str, Any] | None = None,
    replaces: str | None = None,
) -> dcc.Certificate:
    """The certificate of an approved record. `record` holds id, version, kind, method, model,
    validation, temp_c, content_sha256, created_at; `device` model, serial, firmware, manufacturer."""
    kind, method = str(record["kind"]), str(record["method"])
    model = record["model"]
    paper, procedure = PAPERS.get(kind, ("", kind))
    results = [dcc.Result(
        "Calibration parameters",
        f"Parameters of the {method} model fitted by least squares; expanded uncertainties from the fit's "
        f"covariance, coverage factor from Student's t at the fit's degrees of freedom.",
        values=parameter_values(model),
    )]  # fmt: skip
    validation = validation_result(record.get("validation") or {}, k_bound=float(coverage_factor(model_dof(model))))
    if validation is not None:
        results.append(validation)
    conditions = []
    if isinstance(record.get("temp_c"), int | float):
        conditions.append(dcc.Value("temperature", "ambient temperature (mean during the measurement)",
                                    float(record["temp_c"]), "degC"))
    if order is not None:
        c = order["customer"]
        customer = dcc.Contact(str(c["name"]), dcc.Address(str(c["city"]), str(c["country_code"]),
                                                           c.get("street") or None, c.get("post_code") or None),
                               c.get("email") or None)  # fmt: skip
    else:
        customer = laboratory.contact()
    ids = [
        dcc.Identification("calibrationLaboratory", f"record {record['id']} version {record['version']}",
                           "calibration record"),
        dcc.Identification("calibrationLaboratory", str(record["content_sha256"]), "record SHA-256"),
        dcc.Identification("calibrationLaboratory", approval.event_sha256, "approval event SHA-256"),
    ]  # fmt: skip
    if order is not None:
        ids.insert(0, dcc.Identification("customer", str(order["lims_order_id"]), "order"))
    statements = [
        (f"Expanded uncertainties U = k·u are stated with the coverage factor k for a coverage probability of "
        f"about {COVERAGE:.0%} (normal distribution)."),
        (f"The results relate only to the item calibrated. This certificate was approved by {approval.actor} on "
        f"{approval.at.astimezone(dt.UTC):%Y-%m-%d %H:%M} UTC ({approval.meaning}), bound to the record hash "
        f"{approval.record_sha256}."),
    ]  # fmt: skip
    if order is None:
        statements.append("In-house calibration: no customer order names this record.")
    persons = (
        dcc.Person(operator, "operator", statement="ran the calibration"),
        dcc.Person(approval.actor, "approver", main_signer=True,
                   statement=f"{approval.meaning} on {approval.at.astimezone(dt.UTC):%Y-%m-%dT%H:%M:%SZ}"
                             + (f": {approval.note}" if approval.note else "")),
    )  # fmt: skip
    return dcc.Certificate(
        number=number,
        software_name="tiltlab",
        software_version=software_version,
        begin_on=begin_on,
        end_on=_date(record["created_at"]),
        issued_on=issued_on,
        laboratory=laboratory.contact(),
        laboratory_code=laboratory.accreditation or None,
        customer=customer,
        item=dcc.Item(
            name=str(device.get("name") or f"inclinometer {device['model']}"),
            model=str(device["model"]),
            serial=str(device["serial"]),
            manufacturer=device.get("manufacturer") or None,
            firmware=device.get("firmware") or None,
            customer_reference=str(order["item_serial"]) if order and order.get("item_serial") else None,
        ),
        persons=persons,
        methods=(dcc.Method(
            name=f"{kind} calibration, method {method}",
            description=f"{KIND_TEXT.get(kind, kind)}; the {method} model of the tiltlab calibration code.",
            references=(paper,) if paper else (),
            procedure=f"tiltlab procedure {procedure}",
        ),),  # fmt: skip
        standards=standards_of(standards),
        conditions=tuple(conditions),
        results=(dcc.MeasurementResult(f"Calibration of the {kind} inclinometer", tuple(results)),),
        country_code=laboratory.country_code,
        identifications=tuple(ids),
        replaces=replaces,
        statements=tuple(statements),
    )
