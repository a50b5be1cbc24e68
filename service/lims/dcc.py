"""Digital Calibration Certificates in PTB's DCC 3.3.0 format: what a certificate says, and its XML.

Pure: a `Certificate` (what the lab asserts) becomes XML bytes; `issue` refuses to hand out a
document that does not validate against the shipped schemas (dcc_schema). Units are D-SI
(dcc_numbers), values are rounded as GUM 7.2.6 recommends, parameters carry their covariance
beside their expanded uncertainties, and every `tiltlab_*` refType used is defined in the file.
Nothing here reads the database or the clock: the same content always gives the same bytes.
`render_html` (dcc_html) turns issued bytes into a printable page.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

from service.lims.dcc_model import (
    REFTYPE_LINK,
    REFTYPE_NAMESPACE,
    REFTYPES,
    Address,
    CalibratingLaboratory,
    Certificate,
    Column,
    Condition,
    Contact,
    Covariance,
    Identification,
    Item,
    MeasurementResult,
    Method,
    Person,
    ReferenceStandard,
    Result,
    Statement,
    Value,
)
from service.lims.dcc_numbers import (
    at_decimals,
    dsi_product,
    dsi_unit,
    factor,
    gum_decimals,
    gum_pair,
    plain,
)
from service.lims.dcc_schema import (
    DCC_NS,
    DCC_VERSION,
    DSIG_NS,
    SCHEMA_DIR,
    SI_NS,
    InvalidCertificate,
    certificate_errors,
    dcc_schema,
    validate,
)

__all__ = [
    "Address",
    "CalibratingLaboratory",
    "Certificate",
    "Statement",
    "Column",
    "Condition",
    "Contact",
    "Covariance",
    "Identification",
    "Item",
    "MeasurementResult",
    "Method",
    "Person",
    "REFTYPES",
    "REFTYPE_LINK",
    "REFTYPE_NAMESPACE",
    "ReferenceStandard",
    "Result",
    "Value",
    "DCC_NS",
    "DCC_VERSION",
    "DSIG_NS",
    "SCHEMA_DIR",
    "SI_NS",
    "InvalidCertificate",
    "certificate_errors",
    "dcc_schema",
    "dsi_unit",
    "issue",
    "render_html",
    "unique_identifier",
    "validate",
]

SIGNING_CERT_NAME = "SHA-256 of the certificate that signs this file"
# the DCC's statements of conformity we make
CONFORMITY = ("pass", "fail", "conditionalPass", "conditionalFail")

ET.register_namespace("dcc", DCC_NS)
ET.register_namespace("si", SI_NS)
ET.register_namespace("ds", DSIG_NS)

# ---------------------------------------------------------------- XML


def _q(ns: str, tag: str) -> str:
    return f"{{{ns}}}{tag}"


def _el(
    parent: ET.Element, tag: str, text: str | None = None, ns: str = DCC_NS, **attrs: str
) -> ET.Element:
    element = ET.SubElement(
        parent, _q(ns, tag), {name.replace("_", ""): value for name, value in attrs.items()}
    )
    if text is not None:
        element.text = text
    return element


def _text(parent: ET.Element, tag: str, text: str, lang: str) -> ET.Element:
    holder = _el(parent, tag)
    _el(holder, "content", text, lang=lang)
    return holder


def _rich(parent: ET.Element, tag: str, text: str, lang: str) -> None:
    if text.strip():
        _text(parent, tag, text, lang)


def _location(parent: ET.Element, a: Address) -> None:
    loc = _el(parent, "location")
    _el(loc, "city", a.city)
    _el(loc, "countryCode", a.country_code)
    if a.post_code:
        _el(loc, "postCode", a.post_code)
    if a.street:
        _el(loc, "street", a.street)


def _contact(parent: ET.Element, tag: str, c: Contact, lang: str) -> ET.Element:
    element = _el(parent, tag)
    _text(element, "name", c.name, lang)
    if c.email:
        _el(element, "eMail", c.email)
    _location(element, c.address)
    return element


def _identifications(parent: ET.Element, ids: Sequence[Identification], lang: str) -> None:
    if not ids:
        return
    holder = _el(parent, "identifications")
    for identification in ids:
        element = _el(holder, "identification")
        _el(element, "issuer", identification.issuer)
        _el(element, "value", identification.value)
        _text(element, "name", identification.name, lang)


def _check_mu(u: float, k: float | None, p: float | None, what: str) -> tuple[float, float]:
    """The coverage factor and probability of an expanded uncertainty, checked."""
    if k is None or p is None:
        raise InvalidCertificate(
            f"{what}: an expanded uncertainty needs its coverage factor and probability"
        )
    if not (u >= 0 and k >= 1 and 0 < p <= 1):
        raise InvalidCertificate(
            f"{what}: U={u}, k={k}, p={p}: U >= 0, k >= 1 and 0 < p <= 1 are needed"
        )
    return k, p


def _quantity(parent: ET.Element, v: Value, lang: str) -> None:
    element = _el(parent, "quantity", refType=v.ref_type)
    _text(element, "name", v.name, lang)
    if v.note:
        _text(element, "description", v.note, lang)
    real = _el(element, "real", ns=SI_NS)
    _el(real, "label", v.label, ns=SI_NS)
    if v.expanded_u is None and v.standard_u is not None:
        if not v.standard_u >= 0:
            raise InvalidCertificate(f"{v.label}: standard uncertainty {v.standard_u} is not >= 0")
        value, standard_u, _ = gum_pair(v.value, v.standard_u, v.label)
        _el(real, "value", value, ns=SI_NS)
        _el(real, "unit", dsi_unit(v.unit), ns=SI_NS)
        mu = _el(_el(real, "measurementUncertaintyUnivariate", ns=SI_NS), "standardMU", ns=SI_NS)
        _el(mu, "valueStandardMU", standard_u, ns=SI_NS)
        if v.distribution:
            _el(mu, "distribution", v.distribution, ns=SI_NS)
        return
    if v.expanded_u is None:
        _el(real, "value", plain(v.value, v.label), ns=SI_NS)
        _el(real, "unit", dsi_unit(v.unit), ns=SI_NS)
        return
    k, probability = _check_mu(v.expanded_u, v.k, v.probability, v.label)
    value, expanded_u, _ = gum_pair(v.value, v.expanded_u, v.label)
    _el(real, "value", value, ns=SI_NS)
    _el(real, "unit", dsi_unit(v.unit), ns=SI_NS)
    mu = _el(_el(real, "measurementUncertaintyUnivariate", ns=SI_NS), "expandedMU", ns=SI_NS)
    _el(mu, "valueExpandedMU", expanded_u, ns=SI_NS)
    _el(mu, "coverageFactor", factor(k, v.label), ns=SI_NS)
    _el(mu, "coverageProbability", plain(probability, v.label), ns=SI_NS)
    if v.distribution:
        _el(mu, "distribution", v.distribution, ns=SI_NS)


def _column_pairs(c: Column) -> tuple[list[tuple[str, str, int]], Sequence[float], float]:
    """Each value with its U as GUM writes them, the coverage factors and the probability: one
    uncertainty and factor per value, each checked."""
    n = len(c.values)
    if (
        c.expanded_u is None
        or len(c.expanded_u) != n
        or c.k is None
        or len(c.k) != n
        or c.probability is None
    ):
        raise InvalidCertificate(
            f"column {c.label}: {n} values need {n} uncertainties, coverage factors and a "
            "probability"
        )
    pairs = []
    for i, (value, expanded_u, k) in enumerate(zip(c.values, c.expanded_u, c.k, strict=True)):
        _check_mu(expanded_u, k, c.probability, f"column {c.label}[{i}]")
        pairs.append(gum_pair(value, expanded_u, c.label))
    return pairs, c.k, c.probability


def _plain_values(c: Column, decimals: Sequence[int] | None) -> str:
    """A column without uncertainties of its own: each value to its row's decimals, else plain."""
    return " ".join(
        at_decimals(value, decimals[i], c.label) if decimals else plain(value, c.label)
        for i, value in enumerate(c.values)
    )


def _column(parent: ET.Element, c: Column, decimals: Sequence[int] | None, lang: str) -> None:
    """One column; without uncertainties of its own, its values take the row's decimals (those of
    the row's U)."""
    if len(c.values) == 0:
        raise InvalidCertificate(f"column {c.label}: no values")
    element = _el(parent, "quantity", refType=c.ref_type or "tiltlab_table")
    _text(element, "name", c.name, lang)
    lst = _el(element, "realListXMLList", ns=SI_NS)
    _el(lst, "labelXMLList", c.label, ns=SI_NS)
    if c.expanded_u is None:
        _el(lst, "valueXMLList", _plain_values(c, decimals), ns=SI_NS)
        _el(lst, "unitXMLList", dsi_unit(c.unit), ns=SI_NS)
        return
    pairs, ks, probability = _column_pairs(c)
    _el(lst, "valueXMLList", " ".join(pair[0] for pair in pairs), ns=SI_NS)
    _el(lst, "unitXMLList", dsi_unit(c.unit), ns=SI_NS)
    mu = _el(
        _el(lst, "measurementUncertaintyUnivariateXMLList", ns=SI_NS), "expandedMUXMLList", ns=SI_NS
    )
    _el(mu, "valueExpandedMUXMLList", " ".join(pair[1] for pair in pairs), ns=SI_NS)
    _el(mu, "coverageFactorXMLList", " ".join(factor(k, c.label) for k in ks), ns=SI_NS)
    _el(mu, "coverageProbabilityXMLList", plain(probability, c.label), ns=SI_NS)
    if c.distribution:
        _el(mu, "distributionXMLList", c.distribution, ns=SI_NS)


def _check_covariance_shape(c: Covariance) -> None:
    """n labels need n values, units and factors, and an n×n matrix."""
    n = len(c.labels)
    if (
        not n
        or any(len(part) != n for part in (c.values, c.units, c.k, c.matrix))
        or any(len(row) != n for row in c.matrix)
    ):
        raise InvalidCertificate(
            f"parameter covariance: {n} labels need {n} values, units, factors and an {n}x{n} "
            "matrix"
        )


def _covariance_pairs(c: Covariance) -> list[tuple[str, str, int]]:
    """Each parameter's value and U = k·√variance as GUM writes them; a negative variance is
    refused."""
    pairs = []
    for i, label in enumerate(c.labels):
        var = float(c.matrix[i][i])
        if not var >= 0:
            raise InvalidCertificate(f"parameter covariance: the variance of {label} is {var}")
        pairs.append(gum_pair(c.values[i], c.k[i] * var**0.5, label))
    return pairs


def _covariance_columns(region: ET.Element, c: Covariance) -> None:
    """The covariance matrix column by column, each entry in the product of its two units."""
    n = len(c.labels)
    matrix = _el(region, "covarianceMatrixXMLList", ns=SI_NS)
    for j in range(n):
        cov = _el(_el(matrix, "columnXMLList", ns=SI_NS), "covarianceXMLList", ns=SI_NS)
        _el(
            cov,
            "valueXMLList",
            " ".join(plain(c.matrix[i][j], "covariance") for i in range(n)),
            ns=SI_NS,
        )
        _el(
            cov,
            "unitXMLList",
            " ".join(dsi_product(c.units[i], c.units[j]) for i in range(n)),
            ns=SI_NS,
        )


def _covariance(parent: ET.Element, c: Covariance, lang: str) -> None:
    _check_covariance_shape(c)
    element = _el(parent, "quantity", refType="tiltlab_parameterVector")
    _text(element, "name", "fitted parameters with their covariance", lang)
    if c.note:
        _text(element, "description", c.note, lang)
    lst = _el(element, "realListXMLList", ns=SI_NS)
    _el(lst, "labelXMLList", " ".join(c.labels), ns=SI_NS)
    pairs = _covariance_pairs(c)
    _el(lst, "valueXMLList", " ".join(pair[0] for pair in pairs), ns=SI_NS)
    _el(lst, "unitXMLList", " ".join(dsi_unit(unit) for unit in c.units), ns=SI_NS)
    mu = _el(
        _el(lst, "measurementUncertaintyUnivariateXMLList", ns=SI_NS), "expandedMUXMLList", ns=SI_NS
    )
    _el(mu, "valueExpandedMUXMLList", " ".join(pair[1] for pair in pairs), ns=SI_NS)
    _el(mu, "coverageFactorXMLList", " ".join(factor(k, "k") for k in c.k), ns=SI_NS)
    _el(mu, "coverageProbabilityXMLList", plain(c.probability, "p"), ns=SI_NS)
    _el(mu, "distributionXMLList", c.distribution, ns=SI_NS)
    region = _el(
        _el(lst, "measurementUncertaintyMultivariateXMLList", ns=SI_NS),
        "ellipsoidalRegionMUXMLList",
        ns=SI_NS,
    )
    _covariance_columns(region, c)
    _el(region, "coverageFactorXMLList", factor(c.region_k, "region k"), ns=SI_NS)
    _el(region, "coverageProbabilityXMLList", plain(c.probability, "p"), ns=SI_NS)
    _el(region, "distributionXMLList", c.distribution, ns=SI_NS)


def _row_decimals(columns: Sequence[Column]) -> list[int] | None:
    """Per row, the decimals of the first column's U in it: the other columns of the row are written
    to them."""
    for column in columns:
        if column.expanded_u:
            return [
                gum_decimals(expanded_u) if expanded_u > 0 else 6
                for expanded_u in column.expanded_u
            ]
    return None


def _unique_labels(r: Result) -> None:
    """Software reads a quantity by its label: two quantities of one list never share one."""
    for what, labels in (
        ("values", [value.label for value in r.values]),
        ("table", [column.label for column in r.columns]),
    ):
        seen = {label for label in labels if labels.count(label) > 1}
        if seen:
            raise InvalidCertificate(
                f"result {r.name!r}: the label(s) {', '.join(sorted(seen))} appear more than once "
                f"in its {what}"
            )


def _table(data: ET.Element, r: Result, lang: str) -> None:
    """A result's table: columns of equal length, written to the decimals of each row's U."""
    lengths = {len(column.values) for column in r.columns}
    if len(lengths) != 1:
        raise InvalidCertificate(
            f"result {r.name!r}: its columns differ in length {sorted(lengths)}"
        )
    table = _el(data, "list", refType=r.table_ref_type)
    decimals = _row_decimals(r.columns)
    for column in r.columns:
        _column(table, column, decimals, lang)


def _result(parent: ET.Element, r: Result, lang: str) -> None:
    if not r.values and not r.columns and r.covariance is None:
        raise InvalidCertificate(f"result {r.name!r} has no values")
    element = _el(parent, "result")
    _text(element, "name", r.name, lang)
    _rich(element, "description", r.description, lang)
    _unique_labels(r)
    data = _el(element, "data")
    if r.values:
        lst = _el(data, "list", refType="tiltlab_values")
        for value in r.values:
            _quantity(lst, value, lang)
    if r.columns:
        _table(data, r, lang)
    if r.covariance is not None:
        _covariance(_el(data, "list", refType="tiltlab_values"), r.covariance, lang)


def _standard(parent: ET.Element, s: ReferenceStandard, lang: str) -> None:
    """A reference standard: its certificate (number, SHA-256, who issued it), its identity, and the
    uncertainty its certificate states as numbers (`measuringEquipmentQuantities`)."""
    element = _el(parent, "measuringEquipment", refType="basic_referenceStandard")
    _text(element, "name", s.name, lang)
    lab = s.calibrated_by
    description = (
        f"Calibrated on {s.calibrated_on.isoformat()}, due for recalibration on "
        f"{s.due_on.isoformat()}"
        + (f", by {lab.described()}" if lab else "")
        + "."
        + (f" Its certificate states the uncertainty as: {s.uncertainty}." if s.uncertainty else "")
    )
    _text(element, "description", description, lang)
    cert = _el(element, "certificate")
    _text(
        cert,
        "referral",
        f"calibration certificate {s.certificate_number} of {s.name}"
        + (f", issued by {lab.described()}" if lab else ""),
        lang,
    )
    _el(cert, "referralID", s.certificate_number)
    _el(cert, "procedure", "SHA-256")
    _el(cert, "value", s.certificate_sha256)
    _text(
        cert,
        "description",
        "the SHA-256 of the standard's calibration certificate file as the laboratory "
        "registered it",
        lang,
    )
    _el(cert, "inValidityRange", "true" if s.valid_on_performance_date else "false")
    _el(cert, "traceable", "true" if lab is not None else "false")
    if s.model:
        _el(element, "model", s.model)
    _identifications(element, _standard_identifications(s), lang)
    if s.expanded_uncertainty is not None and s.coverage_factor is not None:
        _standard_quantities(element, s, s.expanded_uncertainty, s.coverage_factor, lang)


def _standard_identifications(s: ReferenceStandard) -> list[Identification]:
    """A standard's serial number, and its certificate number and the accreditation of the
    laboratory that issued it, where that laboratory is named."""
    lab = s.calibrated_by
    ids = [Identification("manufacturer", s.serial, "serial number")]
    if lab is not None:
        ids.append(
            Identification(
                "calibrationLaboratory",
                s.certificate_number,
                f"calibration certificate number, issued by {lab.name}",
            )
        )
        if lab.accreditation:
            ids.append(
                Identification(
                    "calibrationLaboratory",
                    lab.accreditation,
                    f"accreditation of {lab.name}, which calibrated the standard",
                )
            )
    return ids


def _standard_quantities(
    element: ET.Element,
    s: ReferenceStandard,
    expanded_uncertainty: float,
    coverage_factor: float,
    lang: str,
) -> None:
    """The uncertainty a standard's certificate states, as numbers: U, k, p and the u = U/k that
    enters the results."""
    qs = _el(element, "measuringEquipmentQuantities")
    kind = "tiltlab_standardUncertaintyStatement"
    for value in (
        Value(
            "expanded_uncertainty_of_the_standard",
            "expanded uncertainty U of the standard's angle, as its certificate states it",
            expanded_uncertainty,
            s.unit,
            ref_type=kind,
        ),
        Value(
            "coverage_factor_of_the_standard",
            "coverage factor k of that expanded uncertainty",
            coverage_factor,
            "1",
            ref_type=kind,
        ),
        Value(
            "coverage_probability_of_the_standard",
            "coverage probability p of that expanded uncertainty",
            s.coverage_probability,
            "1",
            ref_type=kind,
        ),
        Value(
            "standard_uncertainty_of_the_standard",
            "standard uncertainty u = U/k that enters the results",
            expanded_uncertainty / coverage_factor,
            s.unit,
            ref_type=kind,
        ),
    ):
        quantity = _el(qs, "measuringEquipmentQuantity", refType=value.ref_type)
        _text(quantity, "name", value.name, lang)
        real = _el(quantity, "real", ns=SI_NS)
        _el(real, "label", value.label, ns=SI_NS)
        _el(real, "value", plain(value.value, value.label), ns=SI_NS)
        _el(real, "unit", dsi_unit(value.unit), ns=SI_NS)


def _software(parent: ET.Element, name: str, release: str, kind: str, lang: str) -> None:
    sw = _el(parent, "software")
    _text(sw, "name", name, lang)
    _el(sw, "release", release)
    _el(sw, "type", kind)


def _core_data(adm: ET.Element, c: Certificate, lang: str) -> None:
    """The certificate's core data: country, language, number, identifications, dates, and the
    certificate it substitutes."""
    core = _el(adm, "coreData")
    _el(core, "countryCodeISO3166_1", c.country_code)
    _el(core, "usedLangCodeISO639_1", lang)
    _el(core, "mandatoryLangCodeISO639_1", lang)
    _el(core, "uniqueIdentifier", c.number)
    ids = list(c.identifications)
    if c.signing_cert_sha256:
        ids.append(
            Identification("calibrationLaboratory", c.signing_cert_sha256, SIGNING_CERT_NAME)
        )
    _identifications(core, ids, lang)
    _el(core, "beginPerformanceDate", c.begin_on.isoformat())
    _el(core, "endPerformanceDate", c.end_on.isoformat())
    _el(core, "performanceLocation", c.location)
    _el(core, "issueDate", c.issued_on.isoformat())
    if c.replaces:
        ras = _el(core, "reportAmendedSubstituted")
        _el(ras, "typeOfChange", "substituted")
        _el(ras, "replacedUniqueIdentifier", c.replaces)


def _item(adm: ET.Element, c: Certificate, lang: str) -> None:
    """The calibrated item: name, firmware, manufacturer, model and at least one
    identification."""
    item = _el(_el(adm, "items"), "item")
    _text(item, "name", c.item.name, lang)
    if c.item.firmware:
        _software(_el(item, "installedSoftwares"), "firmware", c.item.firmware, "firmware", lang)
    if c.item.manufacturer:
        _text(_el(item, "manufacturer"), "name", c.item.manufacturer, lang)
    if c.item.model:
        _el(item, "model", c.item.model)
    if not c.item.identifications:
        raise InvalidCertificate("the item needs an identification (its serial number)")
    _identifications(item, c.item.identifications, lang)


def _administrative(root: ET.Element, c: Certificate, lang: str) -> ET.Element:
    adm = _el(root, "administrativeData")
    _software(_el(adm, "dccSoftware"), c.software_name, c.software_version, "application", lang)
    _el(adm, "refTypeDefinitions")  # filled once the rest is written: it defines what is used
    _core_data(adm, c, lang)
    _item(adm, c, lang)

    lab = _el(adm, "calibrationLaboratory")
    if c.laboratory_code:
        _el(lab, "calibrationLaboratoryCode", c.laboratory_code)
    _contact(lab, "contact", c.laboratory, lang)

    persons = _el(adm, "respPersons")
    for person in c.persons:
        element = _el(persons, "respPerson")
        _text(_el(element, "person"), "name", person.name, lang)
        _rich(element, "description", person.statement, lang)
        _el(element, "role", person.role)
        _el(element, "mainSigner", "true" if person.main_signer else "false")
    _contact(adm, "customer", c.customer, lang)
    if c.statements:
        stmts = _el(adm, "statements")
        for st in c.statements:
            _statement(stmts, st if isinstance(st, Statement) else Statement(st), lang)
    return adm


def _statement(parent: ET.Element, st: Statement, lang: str) -> None:
    """A statement; one of conformity carries its outcome and the figures it rests on (dcc:data)."""
    element = _el(parent, "statement", **({"refType": st.ref_type} if st.ref_type else {}))
    if st.name:
        _text(element, "name", st.name, lang)
    if st.norm:
        _el(element, "norm", st.norm)
    _text(element, "declaration", st.declaration, lang)
    if st.conformity is not None:
        if st.conformity not in CONFORMITY:
            raise InvalidCertificate(
                f"statement {st.name!r}: conformity {st.conformity!r} is not one of {CONFORMITY}"
            )
        _el(element, "conformity", st.conformity)
    if st.values:
        _unique_labels(Result(st.name or "statement", values=st.values))
        data = _el(element, "data")
        for value in st.values:
            _quantity(data, value, lang)


def _used_reftypes(root: ET.Element) -> list[str]:
    """Every tiltlab_* refType the document uses, sorted, each once."""
    return sorted(
        {
            ref_type
            for element in root.iter()
            for ref_type in (element.get("refType") or "").split()
            if ref_type.startswith("tiltlab_")
        }
    )


def _define_reftypes(root: ET.Element, lang: str) -> None:
    """A refTypeDefinition for every tiltlab_* refType the document uses; an undefined one is
    refused."""
    holder = root.find(f"{_q(DCC_NS, 'administrativeData')}/{_q(DCC_NS, 'refTypeDefinitions')}")
    assert holder is not None
    used = _used_reftypes(root)
    unknown = [ref_type for ref_type in used if ref_type not in REFTYPES]
    if unknown:
        raise InvalidCertificate(f"refType(s) {', '.join(unknown)} have no definition")
    if not used:
        adm = root.find(_q(DCC_NS, "administrativeData"))
        assert adm is not None
        adm.remove(holder)
        return
    for ref_type in used:
        element = _el(holder, "refTypeDefinition", refType=ref_type)
        _text(element, "name", ref_type, lang)
        _text(element, "description", REFTYPES[ref_type], lang)
        _el(element, "namespace", REFTYPE_NAMESPACE)
        _el(element, "link", REFTYPE_LINK)
        _el(element, "value", ref_type)


def _used_methods(results: ET.Element, c: Certificate, lang: str) -> None:
    """The methods the calibration followed, with their procedure and the papers they rest on."""
    if not c.methods:
        return
    methods = _el(results, "usedMethods")
    for method in c.methods:
        used = _el(methods, "usedMethod")
        _text(used, "name", method.name, lang)
        _rich(used, "description", method.description, lang)
        if method.procedure:
            _el(used, "norm", method.procedure)
        for ref in method.references:
            _el(used, "reference", ref)


def _influence_conditions(results: ET.Element, c: Certificate, lang: str) -> None:
    """The conditions during the calibration, each with its values (a basic_ refType from its label
    where it names none)."""
    if not c.conditions:
        return
    conds = _el(results, "influenceConditions")
    for cond in c.conditions:
        ic = _el(
            conds,
            "influenceCondition",
            refType=cond.ref_type or "basic_" + re.sub(r"[^A-Za-z0-9_]", "_", cond.label),
        )
        _text(ic, "name", cond.name, lang)
        _rich(ic, "description", cond.description, lang)
        data = _el(ic, "data")
        for value in cond.values:
            _quantity(data, value, lang)


def _measurement_results(results: ET.Element, c: Certificate, lang: str) -> None:
    """The measurement results, each with its results; a certificate needs at least one."""
    if not c.results:
        raise InvalidCertificate("a certificate needs at least one measurement result")
    for mr in c.results:
        element = _el(results, "measurementResult")
        _text(element, "name", mr.name, lang)
        _rich(element, "description", mr.description, lang)
        rl = _el(element, "results")
        for result in mr.results:
            _result(rl, result, lang)


def build_xml(c: Certificate) -> bytes:
    """The certificate as DCC 3.3.0 XML (UTF-8). Not yet validated: `issue` does that."""
    lang = c.language
    if not c.persons or sum(person.main_signer for person in c.persons) != 1:
        raise InvalidCertificate(
            "a certificate needs exactly one main signer among its responsible persons"
        )
    root = ET.Element(_q(DCC_NS, "digitalCalibrationCertificate"), {"schemaVersion": DCC_VERSION})
    _administrative(root, c, lang)

    results = _el(root, "measurementResults")
    _used_methods(results, c, lang)
    _software(
        _el(results, "usedSoftware"), c.software_name, c.software_version, "application", lang
    )
    if c.standards:
        eq = _el(results, "measuringEquipments")
        for standard in c.standards:
            _standard(eq, standard, lang)
    _influence_conditions(results, c, lang)
    _measurement_results(results, c, lang)
    if c.comment:
        _el(root, "comment").text = c.comment
    _define_reftypes(root, lang)
    ET.indent(root, space="  ")
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
    ).encode("utf-8")


def issue(c: Certificate, signer: Any = None) -> bytes:
    """Build, sign (when the lab signs its certificates: a service.lims.signature.Signer) and
    validate: the only way certificate bytes leave this module. The signed content names the signing
    certificate's SHA-256, so the certificate the signature carries cannot be exchanged
    unnoticed."""
    certificate = replace(c, signing_cert_sha256=signer.cert_sha256) if signer is not None else c
    xml = build_xml(certificate)
    if signer is not None:
        xml = signer(xml)
    validate(xml)
    return xml


def unique_identifier(xml: bytes) -> str:
    root = ET.fromstring(xml)
    found = root.find(
        f"{_q(DCC_NS, 'administrativeData')}/{_q(DCC_NS, 'coreData')}/"
        f"{_q(DCC_NS, 'uniqueIdentifier')}"
    )
    return (found.text or "").strip() if found is not None else ""


def render_html(xml: bytes) -> str:
    from service.lims.dcc_html import render_html as render

    return render(xml)
