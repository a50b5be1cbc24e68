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

from service.calibration.budget import (
    Component,
    UncertaintyBudget,
    current_names,
    model_dof,
    standard_component,
)
from service.calibration.uncertainty import COVERAGE, coverage_factor
from service.lims import dcc
from service.lims.as_found import AXES, AxisAsFound, MeasuredPoint, as_found, single_reading_noise
from service.lims.conformity import (
    ILAC_G8,
    IN_WORDS,
    ConformityReport,
    Decision,
    ParameterFigure,
    QuantityDecision,
    assess,
)
from service.lims.content_results import (
    NOT_TRACEABLE,
    CertificateRefused,
    ambient_conditions,
    budget_result,
    calibration_points_result,
    indication_error_result,
    parameter_result,
    stage_points_result,
    temperature_condition,
    validation_result,
)
from service.lims.dcc_numbers import gum_pair
from service.lims.facts import (
    CalibrationPoint,
    DeviceFacts,
    OrderFacts,
    RecordConditions,
    RecordFacts,
    StandardFacts,
    StatedRange,
)
from service.storage.specification import DecisionRule, Specification
from service.storage.tokens import Person

__all__ = [
    "Approval",
    "CertificateRefused",
    "Laboratory",
    "MeasuredPoint",
    "build_certificate",
    "model_dof",
    "standards_of",
]

# The papers each kind of calibration follows, and the procedure name the daemon runs it under.
PAPERS: dict[str, tuple[str, str]] = {
    "stage": (
        (
            "Wang S., Chang Y., Cui Y., Liu B.: Error correction for off-axis tilt measurement "
            "using biaxial tilt sensor. Journal of Electronic Measurement and Instrumentation, "
            "doi:10.13382/j.jemi.B2407429"
        ),
        "stage-grid",
    ),
    "rotation": (
        (
            "Cao J., Zhu X., Wu H., Zhang L.: An improved method for measurement of "
            "omni-directional spatial rotation angles (IODSRA), 2016"
        ),
        "rotation",
    ),
    "scale": (
        (
            "Zhong Q., Tan L., Huang X., Wang L., Wang J.: Demarcating measuring unit of "
            "pedestal obliquity measuring system of gyroscope based on least squares method, "
            "doi:10.3969/j.issn.1006-1576.2012.12.019"
        ),
        "scale",
    ),
    "turntable": (
        (
            "Liu X., Zhou Z., Zhang Z., Liu D., Zhu W.: Calibration of inclinometer parameters in "
            "digital zenith camera"
        ),
        "turntable",
    ),
}
KIND_TEXT = {
    "stage": "biaxial inclinometer on a two-axis tilt stage, against a reference inclinometer",
    "rotation": "triaxial inclinometer module on a rotary bench (spatial rotation angles)",
    "scale": "ADC inclinometer channel against the stage and the reference inclinometer (measuring "
    "unit)",
    "turntable": "RS-485 inclinometer on a turntable at symmetric azimuths (scale factors and axis "
    "angle)",
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
        return dcc.Contact(
            self.name,
            dcc.Address(self.city, self.country_code, self.street, self.post_code),
            self.email,
        )


@dataclass(frozen=True)
class Approval:
    """The approval event a certificate rests on (who, when, what it means, and the hash it was
    bound to)."""

    actor: str
    at: dt.datetime
    meaning: str
    record_sha256: str
    event_sha256: str
    note: str = ""
    signer: Person | None = None  # the person behind the actor's token when they signed


def _date(value: dt.date | str) -> dt.date:
    if isinstance(value, dt.datetime):
        return value.astimezone(dt.UTC).date()
    if isinstance(value, dt.date):
        return value
    return dt.date.fromisoformat(str(value)[:10])


def _item_identifications(
    device: DeviceFacts, order: OrderFacts | None, reported: bool
) -> list[dcc.Identification]:
    """The order's item serial, then the instrument's own where it reports a different one; the
    laboratory's device record only when neither names the item."""
    ids: list[dcc.Identification] = []
    if order is not None and order.get("item_serial"):
        ids.append(dcc.Identification("manufacturer", str(order["item_serial"]), "serial number"))
    if reported and device.get("serial") and (not ids or ids[0].value != str(device["serial"])):
        ids.append(
            dcc.Identification(
                "manufacturer", str(device["serial"]), "serial number reported by the instrument"
            )
        )
    if not ids:
        ids.append(
            dcc.Identification(
                "calibrationLaboratory",
                f"device {device.get('id')}",
                "the laboratory's device record (the instrument reports no serial number)",
            )
        )
    return ids


def item_of(device: DeviceFacts, order: OrderFacts | None) -> dcc.Item:
    """What identifies the item: the order's item serial, and the instrument's own serial where it
    reports one; manufacturer and model from the order, else from the instrument's identification.
    Never a port or role."""
    # only an instrument that answers an identification states these
    reported = bool(device.get("firmware"))
    ids = _item_identifications(device, order, reported)
    stated_model = order.get("item_model") if order else None
    model = stated_model or (str(device["model"]) if reported and device.get("model") else None)
    stated_maker = order.get("item_manufacturer") if order else None
    maker = stated_maker or device.get("manufacturer") or None
    return dcc.Item(
        name=f"inclinometer {model}" if model else "inclinometer",
        identifications=tuple(ids),
        model=model,
        manufacturer=maker,
        firmware=device.get("firmware") or None,
    )


def standards_of(
    rows: Iterable[StandardFacts], performed_on: dt.date | None = None
) -> tuple[dcc.ReferenceStandard, ...]:
    """The reference standards as the certificate names them; `performed_on`: the day the
    calibration began."""
    out = []
    for row in rows:
        lab = row.get("calibrated_by") or None
        calibrated_on, due_on = _date(row["calibrated_on"]), _date(row["due_on"])
        expanded_u, k = row.get("expanded_uncertainty_deg"), row.get("coverage_factor")
        out.append(
            dcc.ReferenceStandard(
                name=str(row["name"]),
                serial=str(row["serial"]),
                certificate_number=str(row["certificate_number"]),
                certificate_sha256=str(row["certificate_sha256"]),
                calibrated_on=calibrated_on,
                due_on=due_on,
                uncertainty=str(row.get("uncertainty") or ""),
                model=row.get("model") or None,
                calibrated_by=dcc.CalibratingLaboratory(
                    str(lab["name"]),
                    str(lab["country_code"]),
                    lab.get("accreditation"),
                    lab.get("city"),
                )
                if lab
                else None,
                expanded_uncertainty=float(expanded_u)
                if isinstance(expanded_u, int | float)
                else None,
                coverage_factor=float(k) if isinstance(k, int | float) else None,
                valid_on_performance_date=performed_on is None
                or calibrated_on <= performed_on <= due_on,
            )
        )
    return tuple(out)


def check_traceability(standards: Sequence[dcc.ReferenceStandard], performed_on: dt.date) -> None:
    """A certificate states a traceable result only: at least one registered standard with a numeric
    uncertainty, every standard valid on the day of the calibration and naming the laboratory that
    calibrated it."""
    if not standards:
        raise CertificateRefused(
            f"{NOT_TRACEABLE}: the record was calibrated without a registered reference standard; "
            "no certificate is issued (calibrate again naming a standard in reference_standards)"
        )
    for standard in standards:
        where = (
            f"reference standard {standard.name} (serial {standard.serial}, certificate "
            f"{standard.certificate_number})"
        )
        if not standard.valid_on_performance_date:
            raise CertificateRefused(
                f"{where} was not valid on {performed_on} (calibrated on {standard.calibrated_on}, "
                f"due on {standard.due_on}); no certificate is issued"
            )
        if standard.calibrated_by is None:
            raise CertificateRefused(
                f"{where} does not name the laboratory that calibrated it, so the result's "
                "traceability cannot be stated; register its certificate again with calibrated_by"
            )
    if not any(
        standard.expanded_uncertainty is not None and standard.coverage_factor is not None
        for standard in standards
    ):
        raise CertificateRefused(
            f"{NOT_TRACEABLE}: no reference standard of the record states its uncertainty as a "
            "number; no certificate is issued"
        )


def persons_of(
    approval: Approval, operator: str, operator_person: Person | None, job_id: int | None
) -> tuple[dcc.Person, ...]:
    """The operator who ran the job and the approver as main signer, by person with their
    functions."""
    signer = approval.signer
    if signer is None or not signer.name:
        raise CertificateRefused(
            f"the record was approved with the token {approval.actor!r}, which names no person; a "
            "certificate names the person who authorised it: the record must be approved with a "
            "token that names its person (name and function)"
        )
    if not signer.function:
        raise CertificateRefused(
            f"the record was approved by {signer.name} (token {approval.actor!r}), whose function "
            "was not recorded; a certificate names the authorising person's function"
        )
    when = approval.at.astimezone(dt.UTC)
    approver = dcc.Person(
        signer.name,
        signer.function,
        main_signer=True,
        statement=(
            f"{approval.meaning} of the calibration record on {when:%Y-%m-%dT%H:%M:%SZ} with the "
            f"token {approval.actor!r}" + (f": {approval.note}" if approval.note else "")
        ),
    )
    job = f"job {job_id}" if job_id is not None else "the calibration"
    if operator_person is not None:
        ran = dcc.Person(
            operator_person.name,
            operator_person.function or "operator",
            statement=f"operator: ran {job} (started with the token {operator!r})",
        )
    else:
        ran = dcc.Person(
            operator,
            "operator",
            statement=f"operator: ran {job}; {operator!r} is the name of the token "
            "that started it, which named no person",
        )
    return ran, approver


def _conformity_words(
    quantity: QuantityDecision, decision: Decision, limit: float, shown: str
) -> str:
    """The statement in words: the outcome, the specification, the rule and the worst point (with
    the probability of false acceptance where a point passed)."""
    value, expanded_u, _ = gum_pair(
        decision.worst_error, decision.worst_expanded_u, quantity.quantity
    )
    words = (
        f"{quantity.name[:1].upper()}{quantity.name[1:]}: {IN_WORDS[decision.conformity]}. "
        f"Specification: |error| <= {limit:g}{shown} (largest permissible error, MPE). Decision "
        f"rule: {decision.rule_text()}; U is the expanded uncertainty (95 %) of the error at each "
        f"point. The statement is that of the worst of the {decision.n_points} point(s): error "
        f"{'+' if decision.worst_error > 0 else ''}{value}{shown} with U = {expanded_u}{shown}."
    )
    if decision.largest_false_acceptance is not None:
        pfa = decision.largest_false_acceptance
        words += " The largest probability of false acceptance over the points that pass is " + (
            "below 0.01 %." if pfa < 1e-4 else f"{pfa:.2%}."
        )
    return words


def _conformity_values(decision: Decision, limit: float, unit: str) -> list[dcc.Value]:
    """The figures a statement of conformity rests on: the MPE, the worst point's error with its U,
    the guard band and the probability of false acceptance where they apply."""
    k = decision.worst_expanded_u / _u_of(decision) if _u_of(decision) > 0 else None
    values = [
        dcc.Value(
            "max_permissible_error",
            "largest permissible error (MPE)",
            limit,
            unit,
            ref_type="tiltlab_conformityStatement",
        ),
        dcc.Value(
            "worst_error",
            "error at the worst point, with its expanded uncertainty",
            decision.worst_error,
            unit,
            decision.worst_expanded_u if k else None,
            k,
            COVERAGE if k else None,
            distribution="student-t" if k and math.isfinite(decision.worst_dof) else "normal",
            ref_type="tiltlab_conformityStatement",
        ),
    ]
    if decision.rule is DecisionRule.GUARDED_ACCEPTANCE:
        values.append(
            dcc.Value(
                "guard_band_fraction",
                "guard band w as a fraction of U",
                decision.guard_band_fraction,
                "1",
                ref_type="tiltlab_conformityStatement",
            )
        )
    if decision.largest_false_acceptance is not None:
        values.append(
            dcc.Value(
                "largest_probability_of_false_acceptance",
                "largest probability of false acceptance",
                float(f"{decision.largest_false_acceptance:.2g}"),
                "1",
                ref_type="tiltlab_conformityStatement",
            )
        )
    return values


def conformity_statements(report: ConformityReport) -> list[dcc.Statement]:
    """One statement of conformity per quantity the specification names (17025 7.8.6, ILAC-G8)."""
    out = []
    spec = report.specification
    for quantity in report.quantities:
        decision = quantity.decision
        name = f"statement of conformity: {quantity.name}"
        if decision is None:
            out.append(
                dcc.Statement(
                    f"No statement of conformity for {quantity.name}: {quantity.reason}.",
                    name=name,
                    ref_type="tiltlab_conformityStatement",
                )
            )
            continue
        unit = quantity.unit or "1"
        shown = "°" if unit == "deg" else f" {unit}"
        limit = (
            spec.max_permissible_error_deg
            if quantity.quantity in AXES
            else decision.max_permissible_error
        )
        out.append(
            dcc.Statement(
                _conformity_words(quantity, decision, limit, shown),
                name=name,
                conformity=decision.conformity.value,
                norm=ILAC_G8,
                values=tuple(_conformity_values(decision, limit, unit)),
                ref_type="tiltlab_conformityStatement",
            )
        )
    return out


def _u_of(d: Decision) -> float:
    return d.worst_expanded_u / d.worst_k if d.worst_k > 0 else 0.0


def parameter_figures(params: dcc.Result) -> dict[str, ParameterFigure]:
    """The parameters as the certificate states them (value, U, k), for statements about named
    parameters."""
    return {
        value.label: ParameterFigure(value.value, value.expanded_u, value.k, value.unit)
        for value in params.values
    }


def _point_results(
    measured_points: Sequence[MeasuredPoint],
    calibration_points: Sequence[CalibrationPoint],
    standards: Sequence[dcc.ReferenceStandard],
    conditions: RecordConditions,
    stated_range: StatedRange | None,
) -> tuple[list[dcc.Result], dict[str, AxisAsFound] | None]:
    """The calibration points and, for a stage job's measured points, the indication errors as
    found; with those errors, which statements of conformity rest on (None without measured
    points)."""
    if not measured_points:
        points = calibration_points_result(calibration_points, stated_range)
        return ([points] if points is not None else []), None
    found = found_as(measured_points, standards, conditions)
    points = stage_points_result(measured_points, found, stated_range)
    errors = indication_error_result(measured_points, found)
    return [result for result in (points, errors) if result is not None], found


def _budget_stated(
    budget: UncertaintyBudget | None,
    conditions: RecordConditions,
    measured_points: Sequence[MeasuredPoint],
) -> dcc.Result | None:
    """The uncertainty budget, with a single reading's U where the calibration points state how
    many readings each mean took and their spread."""
    fitted = [measured_point for measured_point in measured_points if measured_point.fitted]
    per_point = conditions.get("samples_per_point")
    return budget_result(
        budget,
        int(per_point) if isinstance(per_point, int) else None,
        single_reading_noise(fitted) if fitted else None,
    )


def _influence_conditions(
    record: RecordFacts, budget: UncertaintyBudget | None, conditions: RecordConditions
) -> list[dcc.Condition]:
    """The laboratory's ambient conditions, then the item's internal temperature, where the record
    states them."""
    return ambient_conditions(conditions) + [
        condition for condition in (temperature_condition(record, budget),) if condition is not None
    ]


def _customer(order: OrderFacts) -> dcc.Contact:
    """The customer the order names."""
    customer = order["customer"]
    return dcc.Contact(
        str(customer["name"]),
        dcc.Address(
            str(customer["city"]),
            str(customer["country_code"]),
            customer.get("street") or None,
            customer.get("post_code") or None,
        ),
        customer.get("email") or None,
    )


def _record_identifications(
    record: RecordFacts, approval: Approval, order: OrderFacts | None
) -> list[dcc.Identification]:
    """What ties the certificate to its order, the record (version and hash) and the approval."""
    ids = [
        dcc.Identification(
            "calibrationLaboratory",
            f"record {record['id']} version {record['version']}",
            "calibration record",
        ),
        dcc.Identification(
            "calibrationLaboratory", str(record["content_sha256"]), "record SHA-256"
        ),
        dcc.Identification(
            "calibrationLaboratory", approval.event_sha256, "approval event SHA-256"
        ),
    ]
    if order is not None:
        ids.insert(0, dcc.Identification("customer", str(order["lims_order_id"]), "order"))
    return ids


def _statements(approval: Approval, order: OrderFacts | None) -> list[str | dcc.Statement]:
    """The statements every certificate makes: how uncertainties are stated, who authorised it,
    traceability; and that a calibration without an order is in-house."""
    signer = approval.signer
    assert signer is not None  # persons_of refused an approval without one
    statements: list[str | dcc.Statement] = [
        (
            "Expanded uncertainties U = k·u are stated for a coverage probability of "
            f"{COVERAGE:.0%}; k is Student's t at the degrees of freedom of each uncertainty "
            "(the fit's, or the Welch-Satterthwaite effective degrees of freedom of a "
            "combination), which each quantity's description states. Standard uncertainties u "
            "are stated as such. Uncertainties are rounded to two significant digits and values "
            "to the same decimal place (GUM 7.2.6)."
        ),
        (
            "The results relate only to the item calibrated. This certificate was authorised by "
            f"{signer.described()}, who approved the calibration record on "
            f"{approval.at.astimezone(dt.UTC):%Y-%m-%d %H:%M} UTC ({approval.meaning}), bound to "
            f"the record hash {approval.record_sha256}."
        ),
        (
            "The results are traceable to the SI through the reference standards listed under "
            "measuring equipment, "
            "each calibrated by the laboratory named there and valid on the day of the calibration."
        ),
    ]
    if order is None:
        statements.append("In-house calibration: no customer order names this record.")
    return statements


def _conformity_stated(
    specification: Specification | None,
    found: Mapping[str, AxisAsFound] | None,
    params: dcc.Result,
) -> list[dcc.Statement]:
    """The statements of conformity the order's specification asks for (none without one); refused
    when the record has no measured points to state them on."""
    if specification is None:
        return []
    if found is None:
        raise CertificateRefused(
            "the order asks for statements of conformity, but the record has no measured "
            "points to state them on"
        )
    return conformity_statements(assess(specification, found, parameter_figures(params)))


def build_certificate(
    *,
    number: str,
    record: RecordFacts,
    device: DeviceFacts,
    approval: Approval,
    operator: str,
    laboratory: Laboratory,
    software_version: str,
    issued_on: dt.date,
    begin_on: dt.date,
    standards: Sequence[StandardFacts] = (),
    order: OrderFacts | None = None,
    replaces: str | None = None,
    calibration_points: Sequence[CalibrationPoint] = (),
    measured_points: Sequence[MeasuredPoint] = (),
    operator_person: Person | None = None,
    job_id: int | None = None,
    specification: Specification | None = None,
) -> dcc.Certificate:
    """The certificate of an approved record. `record` holds id, version, kind, method, model,
    validation, temp_c, content_sha256, created_at and optionally budget, calibrated_range and
    conditions; `device` id, model, serial, firmware (the instrument's identity: model and serial
    count as its own only where it reports firmware, i.e. answers an identification), manufacturer;
    `order` lims_order_id, item_serial, item_manufacturer, item_model, customer; `measured_points` a
    stage job's settled points (both sensors), `calibration_points` another kind's fit points
    (`commanded_angle_deg`); `specification` the order's, which asks for statements of conformity.
    CertificateRefused says why a record cannot be certified."""
    kind, method = str(record["kind"]), str(record["method"])
    model = record["model"]
    budget = current_names(record.get("budget") or None)
    conditions = record.get("conditions") or {}
    named_standards = standards_of(standards, begin_on)
    check_traceability(named_standards, begin_on)
    persons = persons_of(approval, operator, operator_person, job_id)
    paper, procedure = PAPERS.get(kind, ("", kind))
    params = parameter_result(model, budget)
    results = [params]
    validation = validation_result(
        record.get("validation") or {},
        k_bound=float(coverage_factor(model_dof(model))),
        budget=budget,
    )
    if validation is not None:
        results.append(validation)
    point_results, found = _point_results(
        measured_points,
        calibration_points,
        named_standards,
        conditions,
        record.get("calibrated_range"),
    )
    results += point_results
    budget_stated = _budget_stated(budget, conditions, measured_points)
    if budget_stated is not None:
        results.append(budget_stated)
    influence = _influence_conditions(record, budget, conditions)
    customer = _customer(order) if order is not None else laboratory.contact()
    ids = _record_identifications(record, approval, order)
    statements = _statements(approval, order)
    statements += _conformity_stated(specification, found, params)
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
        methods=(
            dcc.Method(
                name=f"{kind} calibration, method {method}",
                description=f"{KIND_TEXT.get(kind, kind)}; the {method} model of the tiltlab "
                "calibration code.",
                references=(paper,) if paper else (),
                procedure=f"tiltlab procedure {procedure}",
            ),
        ),
        standards=named_standards,
        conditions=tuple(influence),
        results=(dcc.MeasurementResult(f"Calibration of the {kind} inclinometer", tuple(results)),),
        country_code=laboratory.country_code,
        identifications=tuple(ids),
        replaces=replaces,
        statements=tuple(statements),
    )


def found_as(
    points: Sequence[MeasuredPoint],
    standards: Sequence[dcc.ReferenceStandard],
    conditions: RecordConditions,
) -> dict[str, AxisAsFound]:
    """The indication errors as found at a stage job's points, with the standards' u = U/k in the
    reference values and the sensors' resolutions the record's conditions state."""
    components: list[Component] = [
        standard_component(
            f"{standard.name} (serial {standard.serial}, certificate "
            f"{standard.certificate_number})",
            standard.expanded_uncertainty,
            standard.coverage_factor,
        )
        for standard in standards
        if standard.expanded_uncertainty is not None
        and standard.coverage_factor is not None
        and standard.unit == "deg"
    ]

    def resolution(role: str) -> float | None:
        stated = (conditions.get("resolution_deg") or {}).get(role)
        return float(stated) if isinstance(stated, int | float) and stated > 0 else None

    return as_found(
        points, components, resolution("reference_sensor"), resolution("measurement_sensor")
    )
