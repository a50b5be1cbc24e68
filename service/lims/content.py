"""What a certificate says about one approved calibration record, in the lab's words.

Pure: maps a record (as the API shows it: method, MODEL.json, validation, conditions), the device,
the approval, the order and the reference standards to a `dcc.Certificate`. Storage and the API
gather those facts; nothing here reads them.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from service.calibration.budget import model_dof
from service.calibration.uncertainty import COVERAGE, coverage_factor
from service.lims import dcc
from service.lims.content_results import (
    CertificateRefused,
    budget_result,
    calibration_points_result,
    parameter_result,
    temperature_condition,
    validation_result,
)

__all__ = ["Approval", "CertificateRefused", "Laboratory", "build_certificate", "model_dof", "standards_of"]

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


def _date(value: Any) -> dt.date:
    if isinstance(value, dt.datetime):
        return value.astimezone(dt.UTC).date()
    if isinstance(value, dt.date):
        return value
    return dt.date.fromisoformat(str(value)[:10])


def item_of(device: Mapping[str, Any], order: Mapping[str, Any] | None) -> dcc.Item:
    """What identifies the item: the order's item serial, and the instrument's own serial where it reports one;
    manufacturer and model from the order, else from the instrument's identification. Never a port or role."""
    reported = bool(device.get("firmware"))  # only an instrument that answers an identification states these
    ids: list[dcc.Identification] = []
    if order is not None and order.get("item_serial"):
        ids.append(dcc.Identification("manufacturer", str(order["item_serial"]), "serial number"))
    if reported and device.get("serial") and (not ids or ids[0].value != str(device["serial"])):
        ids.append(dcc.Identification("manufacturer", str(device["serial"]), "serial number reported by the instrument"))
    if not ids:
        ids.append(dcc.Identification("calibrationLaboratory", f"device {device.get('id')}",
                                      "the laboratory's device record (the instrument reports no serial number)"))
    model = (order or {}).get("item_model") or (str(device["model"]) if reported and device.get("model") else None)
    maker = (order or {}).get("item_manufacturer") or device.get("manufacturer") or None
    return dcc.Item(name=f"inclinometer {model}" if model else "inclinometer", identifications=tuple(ids),
                    model=model, manufacturer=maker, firmware=device.get("firmware") or None)


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
    calibration_points: Sequence[Mapping[str, Any]] = (),
) -> dcc.Certificate:
    """The certificate of an approved record. `record` holds id, version, kind, method, model, validation,
    temp_c, content_sha256, created_at and optionally budget and calibrated_range; `device` id, model, serial,
    firmware (the instrument's identity: model and serial count as its own only where it reports firmware,
    i.e. answers an identification), manufacturer; `order` lims_order_id, item_serial, item_manufacturer,
    item_model, customer; `calibration_points` the fit points (`reference_x_deg`, `indication_x_deg`, ...)."""
    kind, method = str(record["kind"]), str(record["method"])
    model = record["model"]
    budget = record.get("budget") or None
    paper, procedure = PAPERS.get(kind, ("", kind))
    results = [parameter_result(model, budget)]
    validation = validation_result(record.get("validation") or {}, k_bound=float(coverage_factor(model_dof(model))),
                                   budget=budget)
    if validation is not None:
        results.append(validation)
    points = calibration_points_result(calibration_points, record.get("calibrated_range"))
    if points is not None:
        results.append(points)
    if (b := budget_result(budget)) is not None:
        results.append(b)
    conditions = [c for c in (temperature_condition(record, budget),) if c is not None]
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
        (f"Expanded uncertainties U = k·u are stated for a coverage probability of {COVERAGE:.0%}; k is Student's t "
         "at the degrees of freedom of each uncertainty (the fit's, or the Welch-Satterthwaite effective degrees of "
         "freedom of a combination), which each quantity's description states. Uncertainties are rounded to two "
         "significant digits and values to the same decimal place (GUM 7.2.6)."),
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
        item=item_of(device, order),
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
