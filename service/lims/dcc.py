"""Digital Calibration Certificates in PTB's DCC 3.3.0 format: build, validate, render.

Pure: a `Certificate` (what the lab asserts) becomes XML bytes; `issue` refuses to hand out a
document that does not validate against the shipped schemas; `render_html` turns issued bytes
into a printable page. Nothing here reads the database or the clock: the caller supplies every
value, so the same content always gives the same bytes.
"""

from __future__ import annotations

import datetime as dt
import html
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import xmlschema

DCC_VERSION = "3.3.0"
DCC_NS = "https://ptb.de/dcc"
SI_NS = "https://ptb.de/si"
DSIG_NS = "http://www.w3.org/2000/09/xmldsig#"
QUDT_NS = "http://qudt.org/vocab/"
SCHEMA_DIR = Path(__file__).resolve().parent / "schemas" / f"dcc-{DCC_VERSION}"

ET.register_namespace("dcc", DCC_NS)
ET.register_namespace("si", SI_NS)


class InvalidCertificate(ValueError):
    """A certificate that does not validate, or content that cannot be written as one."""


# ---------------------------------------------------------------- the schema


@lru_cache(maxsize=1)
def dcc_schema() -> xmlschema.XMLSchema:
    """DCC 3.3.0 with every import mapped to a local file: validation never goes to the network."""
    dsig = Path(xmlschema.__file__).resolve().parent / "schemas" / "DSIG" / "xmldsig-core-schema.xsd"
    return xmlschema.XMLSchema(
        str(SCHEMA_DIR / "dcc.xsd"),
        locations={
            SI_NS: str(SCHEMA_DIR / "SI_Format.xsd"),
            DSIG_NS: str(dsig),
            QUDT_NS: str(SCHEMA_DIR / "qudt-quantitykind-shim.xsd"),
        },
        allow="local",  # local files only, never a URL
    )


def certificate_errors(xml: bytes) -> list[str]:
    """Every reason the document is not a valid DCC 3.3.0, one line each ([] when valid)."""
    try:
        text = xml.decode("utf-8") if isinstance(xml, bytes) else xml
        # defuse: a document handed in for checking may carry entity tricks; none is ever resolved
        errors = list(dcc_schema().iter_errors(xmlschema.XMLResource(text, defuse="always", allow="none")))
    except (ET.ParseError, xmlschema.XMLSchemaException, UnicodeDecodeError) as exc:
        return [f"not well-formed XML: {exc}"]
    return [f"{e.path or '/'}: {e.reason or e.message}" for e in errors]


def validate(xml: bytes) -> None:
    errors = certificate_errors(xml)
    if errors:
        raise InvalidCertificate(f"not a valid DCC {DCC_VERSION} document: {errors[0]}"
                                 + (f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""))


# ---------------------------------------------------------------- units

# The lab's unit words (MODEL.json, field-name suffixes) to D-SI unit strings.
_DSI_UNIT = {
    "deg": r"\degree", "degree": r"\degree", "arcsec": r"\arcsecond", "arcmin": r"\arcminute",
    "rad": r"\radian", "1": r"\one", "count": r"\one", "counts": r"\one", "reading": r"\one",
    "degC": r"\degreeCelsius", "C": r"\degreeCelsius", "K": r"\kelvin", "s": r"\second",
    "m": r"\metre", "mm": r"\milli\metre", "hPa": r"\hecto\pascal", "Pa": r"\pascal", "%": r"\percent",
}  # fmt: skip


def dsi_unit(unit: str) -> str:
    """D-SI unit string for 'deg', 'arcsec/count^2', '1/deg', 'reading/arcsec' and the like.

    A count or a raw reading is a pure number (\\one); an unknown word is refused so that no
    certificate carries a unit nobody can read.
    """
    text = unit.strip()
    if not text:
        raise InvalidCertificate("a quantity has an empty unit")
    num, _, den = text.partition("/")
    parts: list[tuple[str, int]] = []
    for side, sign in ((num, 1), (den, -1)):
        if not side:
            continue
        for factor in side.split("*"):
            word, _, power = factor.strip().partition("^")
            if word not in _DSI_UNIT:
                raise InvalidCertificate(f"unit {unit!r}: {word!r} has no D-SI equivalent")
            try:
                exponent = sign * (int(power) if power else 1)
            except ValueError:
                raise InvalidCertificate(f"unit {unit!r}: exponent {power!r} is not an integer") from None
            parts.append((word, exponent))
    significant = [(w, e) for w, e in parts if _DSI_UNIT[w] != r"\one"]
    if not significant:
        return r"\one"
    return "".join(_DSI_UNIT[w] + (rf"\tothe{{{e}}}" if e != 1 else "") for w, e in significant)


# ---------------------------------------------------------------- what a certificate says


@dataclass(frozen=True)
class Address:
    city: str
    country_code: str  # ISO 3166-1 alpha-2
    street: str | None = None
    post_code: str | None = None


@dataclass(frozen=True)
class Contact:
    name: str
    address: Address
    email: str | None = None


@dataclass(frozen=True)
class Person:
    name: str
    role: str
    main_signer: bool = False
    statement: str = ""  # e.g. what the person approved, when, and its meaning


@dataclass(frozen=True)
class Item:
    name: str
    model: str
    serial: str
    manufacturer: str | None = None
    firmware: str | None = None
    customer_reference: str | None = None  # the customer's or LIMS's own id of the item


@dataclass(frozen=True)
class Method:
    name: str
    description: str
    references: tuple[str, ...] = ()  # the papers the method follows
    procedure: str = ""  # the lab's procedure it runs


@dataclass(frozen=True)
class ReferenceStandard:
    name: str
    serial: str
    certificate_number: str
    certificate_sha256: str
    calibrated_on: dt.date
    due_on: dt.date
    uncertainty: str
    model: str | None = None


@dataclass(frozen=True)
class Value:
    """One quantity; an uncertainty, when given, is expanded with its coverage factor and probability."""

    label: str
    name: str
    value: float
    unit: str
    expanded_u: float | None = None
    k: float | None = None
    probability: float | None = None
    note: str = ""


@dataclass(frozen=True)
class Column:
    """One column of a table (a list of values of one quantity), optionally with expanded uncertainties."""

    label: str
    name: str
    values: tuple[float, ...]
    unit: str
    expanded_u: tuple[float, ...] | None = None
    k: tuple[float, ...] | None = None
    probability: float | None = None
    ref_type: str | None = None


@dataclass(frozen=True)
class Result:
    name: str
    description: str = ""
    values: tuple[Value, ...] = ()
    columns: tuple[Column, ...] = ()


@dataclass(frozen=True)
class MeasurementResult:
    name: str
    results: tuple[Result, ...]
    description: str = ""


@dataclass(frozen=True)
class Identification:
    issuer: str  # manufacturer | calibrationLaboratory | customer | owner | other
    value: str
    name: str


@dataclass(frozen=True)
class Certificate:
    number: str
    software_name: str
    software_version: str
    begin_on: dt.date
    end_on: dt.date
    issued_on: dt.date
    laboratory: Contact
    customer: Contact
    item: Item
    persons: tuple[Person, ...]
    methods: tuple[Method, ...]
    standards: tuple[ReferenceStandard, ...]
    conditions: tuple[Value, ...]
    results: tuple[MeasurementResult, ...]
    country_code: str = "DE"
    language: str = "en"
    location: str = "laboratory"
    laboratory_code: str | None = None
    identifications: tuple[Identification, ...] = ()
    replaces: str | None = None  # unique identifier of the certificate this one substitutes
    statements: tuple[str, ...] = field(default_factory=tuple)
    comment: str = ""


# ---------------------------------------------------------------- XML


def _q(ns: str, tag: str) -> str:
    return f"{{{ns}}}{tag}"


def _el(parent: ET.Element, tag: str, text: str | None = None, ns: str = DCC_NS, **attrs: str) -> ET.Element:
    e = ET.SubElement(parent, _q(ns, tag), {k.replace("_", ""): v for k, v in attrs.items()})
    if text is not None:
        e.text = text
    return e


def _num(value: float, what: str) -> str:
    f = float(value)
    if not math.isfinite(f):
        raise InvalidCertificate(f"{what}: {value!r} is not a finite number")
    return repr(f)


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
    e = _el(parent, tag)
    _text(e, "name", c.name, lang)
    if c.email:
        _el(e, "eMail", c.email)
    _location(e, c.address)
    return e


def _identifications(parent: ET.Element, ids: Sequence[Identification], lang: str) -> None:
    if not ids:
        return
    holder = _el(parent, "identifications")
    for i in ids:
        e = _el(holder, "identification")
        _el(e, "issuer", i.issuer)
        _el(e, "value", i.value)
        _text(e, "name", i.name, lang)


def _expanded(parent: ET.Element, u: float, k: float | None, p: float | None, what: str) -> None:
    if k is None or p is None:
        raise InvalidCertificate(f"{what}: an expanded uncertainty needs its coverage factor and probability")
    if u < 0 or k < 1 or not 0 < p <= 1:
        raise InvalidCertificate(f"{what}: U={u}, k={k}, p={p}: U >= 0, k >= 1 and 0 < p <= 1 are needed")
    mu = _el(_el(parent, "measurementUncertaintyUnivariate", ns=SI_NS), "expandedMU", ns=SI_NS)
    _el(mu, "valueExpandedMU", _num(u, what), ns=SI_NS)
    _el(mu, "coverageFactor", _num(k, what), ns=SI_NS)
    _el(mu, "coverageProbability", _num(p, what), ns=SI_NS)
    _el(mu, "distribution", "normal", ns=SI_NS)


def _quantity(parent: ET.Element, v: Value, lang: str) -> None:
    q = _el(parent, "quantity", refType="tiltlab_" + re.sub(r"[^A-Za-z0-9_.-]", "_", v.label))
    _text(q, "name", v.name, lang)
    if v.note:
        _text(q, "description", v.note, lang)
    real = _el(q, "real", ns=SI_NS)
    _el(real, "label", v.label, ns=SI_NS)
    _el(real, "value", _num(v.value, v.label), ns=SI_NS)
    _el(real, "unit", dsi_unit(v.unit), ns=SI_NS)
    if v.expanded_u is not None:
        _expanded(real, v.expanded_u, v.k, v.probability, v.label)


def _column(parent: ET.Element, c: Column, lang: str) -> None:
    n = len(c.values)
    if n == 0:
        raise InvalidCertificate(f"column {c.label}: no values")
    q = _el(parent, "quantity", refType=c.ref_type or ("tiltlab_" + c.label))
    _text(q, "name", c.name, lang)
    lst = _el(q, "realListXMLList", ns=SI_NS)
    _el(lst, "labelXMLList", c.label, ns=SI_NS)
    _el(lst, "valueXMLList", " ".join(_num(v, c.label) for v in c.values), ns=SI_NS)
    _el(lst, "unitXMLList", dsi_unit(c.unit), ns=SI_NS)
    if c.expanded_u is not None:
        if len(c.expanded_u) != n or c.k is None or len(c.k) != n or c.probability is None:
            raise InvalidCertificate(f"column {c.label}: {n} values need {n} uncertainties, coverage factors and a probability")
        for i, (u, k) in enumerate(zip(c.expanded_u, c.k, strict=True)):
            if not (math.isfinite(u) and u >= 0 and math.isfinite(k) and k >= 1):
                raise InvalidCertificate(f"column {c.label}[{i}]: U={u}, k={k}: U >= 0 and k >= 1 are needed")
        mu = _el(_el(lst, "measurementUncertaintyUnivariateXMLList", ns=SI_NS), "expandedMUXMLList", ns=SI_NS)
        _el(mu, "valueExpandedMUXMLList", " ".join(_num(u, c.label) for u in c.expanded_u), ns=SI_NS)
        _el(mu, "coverageFactorXMLList", " ".join(_num(k, c.label) for k in c.k), ns=SI_NS)
        _el(mu, "coverageProbabilityXMLList", _num(c.probability, c.label), ns=SI_NS)
        _el(mu, "distributionXMLList", "normal", ns=SI_NS)


def _result(parent: ET.Element, r: Result, lang: str) -> None:
    if not r.values and not r.columns:
        raise InvalidCertificate(f"result {r.name!r} has no values")
    e = _el(parent, "result")
    _text(e, "name", r.name, lang)
    _rich(e, "description", r.description, lang)
    data = _el(e, "data")
    if r.values:
        lst = _el(data, "list", refType="tiltlab_values")
        for v in r.values:
            _quantity(lst, v, lang)
    if r.columns:
        lengths = {len(c.values) for c in r.columns}
        if len(lengths) != 1:
            raise InvalidCertificate(f"result {r.name!r}: its columns differ in length {sorted(lengths)}")
        table = _el(data, "list", refType="tiltlab_table")
        for c in r.columns:
            _column(table, c, lang)


def _standard(parent: ET.Element, s: ReferenceStandard, lang: str) -> None:
    e = _el(parent, "measuringEquipment", refType="basic_referenceStandard")
    _text(e, "name", s.name, lang)
    _text(e, "description", f"stated uncertainty: {s.uncertainty}; calibrated on {s.calibrated_on.isoformat()},"
                            f" due on {s.due_on.isoformat()}", lang)
    cert = _el(e, "certificate")
    _text(cert, "referral", f"calibration certificate of {s.name}", lang)
    _el(cert, "referralID", s.certificate_number)
    _el(cert, "procedure", "SHA-256")
    _el(cert, "value", s.certificate_sha256)
    _el(cert, "inValidityRange", "true")
    _el(cert, "traceable", "true")
    if s.model:
        _el(e, "model", s.model)
    _identifications(e, [Identification("manufacturer", s.serial, "serial number")], lang)


def build_xml(c: Certificate) -> bytes:
    """The certificate as DCC 3.3.0 XML (UTF-8). Not yet validated: `issue` does that."""
    lang = c.language
    if not c.persons or sum(p.main_signer for p in c.persons) != 1:
        raise InvalidCertificate("a certificate needs exactly one main signer among its responsible persons")
    root = ET.Element(_q(DCC_NS, "digitalCalibrationCertificate"), {"schemaVersion": DCC_VERSION})
    adm = _el(root, "administrativeData")

    sw = _el(_el(adm, "dccSoftware"), "software")
    _text(sw, "name", c.software_name, lang)
    _el(sw, "release", c.software_version)
    _el(sw, "type", "application")

    core = _el(adm, "coreData")
    _el(core, "countryCodeISO3166_1", c.country_code)
    _el(core, "usedLangCodeISO639_1", lang)
    _el(core, "mandatoryLangCodeISO639_1", lang)
    _el(core, "uniqueIdentifier", c.number)
    _identifications(core, c.identifications, lang)
    _el(core, "beginPerformanceDate", c.begin_on.isoformat())
    _el(core, "endPerformanceDate", c.end_on.isoformat())
    _el(core, "performanceLocation", c.location)
    _el(core, "issueDate", c.issued_on.isoformat())
    if c.replaces:
        ras = _el(core, "reportAmendedSubstituted")
        _el(ras, "typeOfChange", "substituted")
        _el(ras, "replacedUniqueIdentifier", c.replaces)

    items = _el(adm, "items")
    item = _el(items, "item")
    _text(item, "name", c.item.name, lang)
    if c.item.firmware:
        fw = _el(_el(item, "installedSoftwares"), "software")
        _text(fw, "name", "firmware", lang)
        _el(fw, "release", c.item.firmware)
        _el(fw, "type", "firmware")
    if c.item.manufacturer:
        man = _el(item, "manufacturer")
        _text(man, "name", c.item.manufacturer, lang)
    _el(item, "model", c.item.model)
    ids = [Identification("manufacturer", c.item.serial, "serial number")]
    if c.item.customer_reference:
        ids.append(Identification("customer", c.item.customer_reference, "customer's item reference"))
    _identifications(item, ids, lang)

    lab = _el(adm, "calibrationLaboratory")
    if c.laboratory_code:
        _el(lab, "calibrationLaboratoryCode", c.laboratory_code)
    _contact(lab, "contact", c.laboratory, lang)

    persons = _el(adm, "respPersons")
    for p in c.persons:
        e = _el(persons, "respPerson")
        person = _el(e, "person")
        _text(person, "name", p.name, lang)
        _rich(e, "description", p.statement, lang)
        _el(e, "role", p.role)
        _el(e, "mainSigner", "true" if p.main_signer else "false")

    _contact(adm, "customer", c.customer, lang)

    if c.statements:
        stmts = _el(adm, "statements")
        for text in c.statements:
            st = _el(stmts, "statement")
            _text(st, "declaration", text, lang)

    results = _el(root, "measurementResults")
    if c.methods:
        methods = _el(results, "usedMethods")
        for m in c.methods:
            e = _el(methods, "usedMethod")
            _text(e, "name", m.name, lang)
            _rich(e, "description", m.description, lang)
            if m.procedure:
                _el(e, "norm", m.procedure)
            for ref in m.references:
                _el(e, "reference", ref)
    used = _el(_el(results, "usedSoftware"), "software")
    _text(used, "name", c.software_name, lang)
    _el(used, "release", c.software_version)
    _el(used, "type", "application")
    if c.standards:
        eq = _el(results, "measuringEquipments")
        for s in c.standards:
            _standard(eq, s, lang)
    if c.conditions:
        conds = _el(results, "influenceConditions")
        for v in c.conditions:
            cond = _el(conds, "influenceCondition", refType="basic_" + v.label)
            _text(cond, "name", v.name, lang)
            _quantity(_el(cond, "data"), v, lang)
    if not c.results:
        raise InvalidCertificate("a certificate needs at least one measurement result")
    for mr in c.results:
        e = _el(results, "measurementResult")
        _text(e, "name", mr.name, lang)
        _rich(e, "description", mr.description, lang)
        rl = _el(e, "results")
        for r in mr.results:
            _result(rl, r, lang)
    if c.comment:
        com = _el(root, "comment")
        com.text = c.comment
    ET.indent(root, space="  ")
    return ('<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n").encode("utf-8")


def issue(c: Certificate) -> bytes:
    """Build and validate: the only way certificate bytes leave this module."""
    xml = build_xml(c)
    validate(xml)
    return xml


# ---------------------------------------------------------------- reading back


def _t(e: ET.Element | None, path: str) -> str:
    if e is None:
        return ""
    found = e.find(path, _NS)
    return (found.text or "").strip() if found is not None else ""


_NS = {"dcc": DCC_NS, "si": SI_NS}


def unique_identifier(xml: bytes) -> str:
    root = ET.fromstring(xml)
    return _t(root, "dcc:administrativeData/dcc:coreData/dcc:uniqueIdentifier")


def render_html(xml: bytes) -> str:
    """A printable page of an issued certificate, made from its XML (so both always say the same)."""
    root = ET.fromstring(xml)
    adm = root.find("dcc:administrativeData", _NS)
    core = adm.find("dcc:coreData", _NS) if adm is not None else None
    esc = html.escape
    number = _t(core, "dcc:uniqueIdentifier")
    out: list[str] = []
    w = out.append
    w("<!doctype html><html lang='en'><head><meta charset='utf-8'>")
    w(f"<title>Calibration certificate {esc(number)}</title><style>{_CSS}</style></head><body>")
    w(f"<h1>Calibration certificate</h1><p class='number'>{esc(number)}</p>")
    ras = core.find("dcc:reportAmendedSubstituted", _NS) if core is not None else None
    if ras is not None:
        w(f"<p class='notice'>This certificate substitutes certificate "
          f"{esc(_t(ras, 'dcc:replacedUniqueIdentifier'))}, which is withdrawn.</p>")
    rows = [
        ("Issued", _t(core, "dcc:issueDate")),
        ("Calibration performed", f"{_t(core, 'dcc:beginPerformanceDate')} to {_t(core, 'dcc:endPerformanceDate')}"),
        ("Location", _t(core, "dcc:performanceLocation")),
    ]
    for ident in core.findall("dcc:identifications/dcc:identification", _NS) if core is not None else []:
        rows.append((_t(ident, "dcc:name/dcc:content"), _t(ident, "dcc:value")))
    _table(w, "Certificate", rows)
    item = adm.find("dcc:items/dcc:item", _NS) if adm is not None else None
    rows = [("Item", _t(item, "dcc:name/dcc:content")), ("Model", _t(item, "dcc:model")),
            ("Manufacturer", _t(item, "dcc:manufacturer/dcc:name/dcc:content"))]
    for ident in item.findall("dcc:identifications/dcc:identification", _NS) if item is not None else []:
        rows.append((_t(ident, "dcc:name/dcc:content").capitalize(), _t(ident, "dcc:value")))
    fw = _t(item, "dcc:installedSoftwares/dcc:software/dcc:release")
    if fw:
        rows.append(("Firmware", fw))
    _table(w, "Calibration item", rows)
    lab = adm.find("dcc:calibrationLaboratory", _NS) if adm is not None else None
    cust = adm.find("dcc:customer", _NS) if adm is not None else None
    _table(w, "Laboratory and customer", [
        ("Laboratory", _contact_text(lab.find("dcc:contact", _NS) if lab is not None else None)),
        ("Accreditation", _t(lab, "dcc:calibrationLaboratoryCode")),
        ("Customer", _contact_text(cust)),
    ])
    rows = []
    for p in adm.findall("dcc:respPersons/dcc:respPerson", _NS) if adm is not None else []:
        main = " (main signer)" if _t(p, "dcc:mainSigner") == "true" else ""
        rows.append((_t(p, "dcc:role") + main, _t(p, "dcc:person/dcc:name/dcc:content") + " — "
                     + _t(p, "dcc:description/dcc:content")))
    _table(w, "Responsible persons", rows)
    results = root.find("dcc:measurementResults", _NS)
    if results is not None:
        rows = [(_t(m, "dcc:name/dcc:content"), " ".join(filter(None, [
            _t(m, "dcc:description/dcc:content"), _t(m, "dcc:norm"),
            "; ".join((r.text or "") for r in m.findall("dcc:reference", _NS))])))
            for m in results.findall("dcc:usedMethods/dcc:usedMethod", _NS)]  # fmt: skip
        _table(w, "Method", rows)
        rows = []
        for eq in results.findall("dcc:measuringEquipments/dcc:measuringEquipment", _NS):
            rows.append((_t(eq, "dcc:name/dcc:content"),
                         (f"serial {_t(eq, 'dcc:identifications/dcc:identification/dcc:value')}; certificate "
                         f"{_t(eq, 'dcc:certificate/dcc:referralID')} (SHA-256 {_t(eq, 'dcc:certificate/dcc:value')}); "
                         f"{_t(eq, 'dcc:description/dcc:content')}")))
        _table(w, "Reference standards", rows)
        rows = [(_t(c, "dcc:name/dcc:content"), _real_text(c.find("dcc:data/dcc:quantity/si:real", _NS)))
                for c in results.findall("dcc:influenceConditions/dcc:influenceCondition", _NS)]
        _table(w, "Conditions", rows)
        for mr in results.findall("dcc:measurementResult", _NS):
            w(f"<h2>{esc(_t(mr, 'dcc:name/dcc:content'))}</h2>")
            desc = _t(mr, "dcc:description/dcc:content")
            if desc:
                w(f"<p>{esc(desc)}</p>")
            for r in mr.findall("dcc:results/dcc:result", _NS):
                _render_result(w, r)
    stmts = [(_t(s, "dcc:declaration/dcc:content")) for s in adm.findall("dcc:statements/dcc:statement", _NS)] \
        if adm is not None else []  # fmt: skip
    if stmts:
        w("<h2>Statements</h2>" + "".join(f"<p>{esc(s)}</p>" for s in stmts))
    sw = adm.find("dcc:dccSoftware/dcc:software", _NS) if adm is not None else None
    w(f"<p class='foot'>Issued by {esc(_t(sw, 'dcc:name/dcc:content'))} {esc(_t(sw, 'dcc:release'))} as a "
      f"DCC {esc(root.get('schemaVersion', ''))} document; the XML certificate is the authoritative version.</p>")
    w("</body></html>\n")
    return "".join(out)


_CSS = (
    "body{font:11pt/1.4 system-ui,sans-serif;margin:2em auto;max-width:60em;color:#111}"
    "h1{margin:0}.number{font-size:1.3em;margin-top:.2em}h2{margin-top:1.4em;border-bottom:1px solid #888}"
    "table{border-collapse:collapse;width:100%;margin:.4em 0}th,td{border:1px solid #bbb;padding:.2em .5em;"
    "text-align:left;vertical-align:top;overflow-wrap:anywhere}td.n{text-align:right;font-variant-numeric:tabular-nums}"
    "th{background:#eee}.notice{border:2px solid #a00;padding:.4em}.foot{margin-top:2em;font-size:.9em;color:#444}"
    "@media print{body{margin:0;max-width:none}h2{break-after:avoid}tr{break-inside:avoid}}"
)

_UNIT_TEXT = {r"\degree": "°", r"\arcsecond": "″", r"\arcminute": "′", r"\one": "", r"\degreeCelsius": "°C",
              r"\radian": "rad"}  # fmt: skip


def _unit_text(unit: str) -> str:
    if unit in _UNIT_TEXT:
        return _UNIT_TEXT[unit]
    return re.sub(r"\\tothe\{(-?\d+)\}", r"^\1", unit).replace("\\", " ").strip()


def _contact_text(c: ET.Element | None) -> str:
    if c is None:
        return ""
    loc = c.find("dcc:location", _NS)
    parts = [_t(c, "dcc:name/dcc:content"), _t(loc, "dcc:street"),
             f"{_t(loc, 'dcc:postCode')} {_t(loc, 'dcc:city')}".strip(), _t(loc, "dcc:countryCode")]
    return ", ".join(p for p in parts if p)


def _real_text(real: ET.Element | None) -> str:
    if real is None:
        return ""
    unit = _unit_text(_t(real, "si:unit"))
    text = f"{_t(real, 'si:value')} {unit}".strip()
    mu = real.find("si:measurementUncertaintyUnivariate/si:expandedMU", _NS)
    if mu is not None:
        text += (f" ± {_t(mu, 'si:valueExpandedMU')} {unit} (k = {_t(mu, 'si:coverageFactor')},"
                 f" p = {_t(mu, 'si:coverageProbability')})")
    return text


def _table(w, title: str, rows: list[tuple[str, str]]) -> None:  # type: ignore[no-untyped-def]
    rows = [(k, v) for k, v in rows if v and v.strip(" —")]
    if not rows:
        return
    w(f"<h2>{html.escape(title)}</h2><table>")
    for k, v in rows:
        w(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>")
    w("</table>")


def _render_result(w, r: ET.Element) -> None:  # type: ignore[no-untyped-def]
    esc = html.escape
    w(f"<h3>{esc(_t(r, 'dcc:name/dcc:content'))}</h3>")
    desc = _t(r, "dcc:description/dcc:content")
    if desc:
        w(f"<p>{esc(desc)}</p>")
    for lst in r.findall("dcc:data/dcc:list", _NS):
        quantities = lst.findall("dcc:quantity", _NS)
        if lst.get("refType") == "tiltlab_table":
            cols = []
            for q in quantities:
                xl = q.find("si:realListXMLList", _NS)
                unit = _unit_text(_t(xl, "si:unitXMLList"))
                values = _t(xl, "si:valueXMLList").split()
                us = _t(xl, "si:measurementUncertaintyUnivariateXMLList/si:expandedMUXMLList/si:valueExpandedMUXMLList").split()
                ks = _t(xl, "si:measurementUncertaintyUnivariateXMLList/si:expandedMUXMLList/si:coverageFactorXMLList").split()
                head = _t(q, "dcc:name/dcc:content") + (f" / {unit}" if unit else "")
                cols.append((head, values))
                if us:
                    cols.append((f"U / {unit}" if unit else "U", us))
                    cols.append(("k", ks))
            w("<table><tr>" + "".join(f"<th>{esc(h)}</th>" for h, _ in cols) + "</tr>")
            for i in range(max((len(v) for _, v in cols), default=0)):
                w("<tr>" + "".join(f"<td class='n'>{esc(v[i] if i < len(v) else '')}</td>" for _, v in cols) + "</tr>")
            w("</table>")
        else:
            w("<table><tr><th>Quantity</th><th>Value</th><th>U</th><th>k</th><th>Unit</th><th>Note</th></tr>")
            for q in quantities:
                real = q.find("si:real", _NS)
                value, u, k = _rounded(_t(real, "si:value"),
                                       _t(real, "si:measurementUncertaintyUnivariate/si:expandedMU/si:valueExpandedMU"),
                                       _t(real, "si:measurementUncertaintyUnivariate/si:expandedMU/si:coverageFactor"))
                w(f"<tr><td>{esc(_t(q, 'dcc:name/dcc:content'))}</td><td class='n'>{esc(value)}</td>"
                  f"<td class='n'>{esc(u)}</td><td class='n'>{esc(k)}</td><td>{esc(_unit_text(_t(real, 'si:unit')))}</td>"
                  f"<td>{esc(_t(q, 'dcc:description/dcc:content'))}</td></tr>")
            w("</table>")


def _rounded(value: str, u: str, k: str) -> tuple[str, str, str]:
    """For people: U to two significant digits and the value to the same decimal place (GUM 7.2.6).

    The XML keeps every digit; this is only the printed form.
    """
    if not u:
        return value, "", ""
    v, uu = float(value), float(u)
    if uu <= 0 or not math.isfinite(uu):
        return value, u, k
    decimals = max(0, 1 - math.floor(math.log10(uu)))
    return f"{v:.{decimals}f}", f"{uu:.{decimals}f}", f"{float(k):.2f}"
