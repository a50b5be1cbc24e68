"""A printable page of an issued DCC certificate, made from its XML (so both always say the
same)."""

from __future__ import annotations

import html
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable

from service.lims.dcc_schema import DCC_NS, SI_NS

_NS = {"dcc": DCC_NS, "si": SI_NS}


def _t(e: ET.Element | None, path: str) -> str:
    if e is None:
        return ""
    found = e.find(path, _NS)
    return (found.text or "").strip() if found is not None else ""


def render_html(xml: bytes) -> str:
    """A printable page of an issued certificate, made from its XML (so both always say the
    same)."""
    root = ET.fromstring(xml)
    adm = root.find("dcc:administrativeData", _NS)
    core = adm.find("dcc:coreData", _NS) if adm is not None else None
    esc = html.escape
    number = _t(core, "dcc:uniqueIdentifier")
    out: list[str] = []
    write = out.append
    write("<!doctype html><html lang='en'><head><meta charset='utf-8'>")
    write(f"<title>Calibration certificate {esc(number)}</title><style>{_CSS}</style></head><body>")
    write(f"<h1>Calibration certificate</h1><p class='number'>{esc(number)}</p>")
    _render_substitution(write, core)
    _table(write, "Certificate", _certificate_rows(core))
    _table(write, "Calibration item", _item_rows(adm))
    _table(write, "Laboratory and customer", _party_rows(adm))
    stmts = adm.findall("dcc:statements/dcc:statement", _NS) if adm is not None else []
    conformity = [st for st in stmts if st.get("refType") == "tiltlab_conformityStatement"]
    _render_conformity(write, conformity)
    _table(write, "Responsible persons", _person_rows(adm))
    results = root.find("dcc:measurementResults", _NS)
    if results is not None:
        _render_measurement_results(write, results)
    _render_statements(write, [st for st in stmts if st not in conformity])
    _render_footer(write, root, adm)
    write("</body></html>\n")
    return "".join(out)


def _render_substitution(write: Callable[[str], None], core: ET.Element | None) -> None:
    """The notice that this certificate substitutes another, which is withdrawn."""
    ras = core.find("dcc:reportAmendedSubstituted", _NS) if core is not None else None
    if ras is not None:
        write(
            f"<p class='notice'>This certificate substitutes certificate "
            f"{html.escape(_t(ras, 'dcc:replacedUniqueIdentifier'))}, which is withdrawn.</p>"
        )


def _certificate_rows(core: ET.Element | None) -> list[tuple[str, str]]:
    """The certificate's dates, location and identifications."""
    rows = [
        ("Issued", _t(core, "dcc:issueDate")),
        (
            "Calibration performed",
            f"{_t(core, 'dcc:beginPerformanceDate')} to {_t(core, 'dcc:endPerformanceDate')}",
        ),
        ("Location", _t(core, "dcc:performanceLocation")),
    ]
    for ident in (
        core.findall("dcc:identifications/dcc:identification", _NS) if core is not None else []
    ):
        rows.append((_t(ident, "dcc:name/dcc:content"), _t(ident, "dcc:value")))
    return rows


def _item_rows(adm: ET.Element | None) -> list[tuple[str, str]]:
    """The calibrated item: name, model, manufacturer, identifications and firmware."""
    item = adm.find("dcc:items/dcc:item", _NS) if adm is not None else None
    rows = [
        ("Item", _t(item, "dcc:name/dcc:content")),
        ("Model", _t(item, "dcc:model")),
        ("Manufacturer", _t(item, "dcc:manufacturer/dcc:name/dcc:content")),
    ]
    for ident in (
        item.findall("dcc:identifications/dcc:identification", _NS) if item is not None else []
    ):
        rows.append((_t(ident, "dcc:name/dcc:content").capitalize(), _t(ident, "dcc:value")))
    firmware = _t(item, "dcc:installedSoftwares/dcc:software/dcc:release")
    if firmware:
        rows.append(("Firmware", firmware))
    return rows


def _party_rows(adm: ET.Element | None) -> list[tuple[str, str]]:
    """The laboratory (with its accreditation) and the customer."""
    lab = adm.find("dcc:calibrationLaboratory", _NS) if adm is not None else None
    cust = adm.find("dcc:customer", _NS) if adm is not None else None
    return [
        (
            "Laboratory",
            _contact_text(lab.find("dcc:contact", _NS) if lab is not None else None),
        ),
        ("Accreditation", _t(lab, "dcc:calibrationLaboratoryCode")),
        ("Customer", _contact_text(cust)),
    ]


def _render_conformity(write: Callable[[str], None], conformity: list[ET.Element]) -> None:
    """The statements of conformity as one table: quantity, outcome, decision and figures."""
    if not conformity:
        return
    esc = html.escape
    write(
        "<h2>Statements of conformity</h2><table "
        "class='verdicts'><tr><th>Quantity</th><th>Statement</th><th>Decision</th>"
        "<th>Figures</th></tr>"
    )
    for st in conformity:
        verdict = _t(st, "dcc:conformity")
        figures = "; ".join(
            f"{_t(quantity, 'dcc:name/dcc:content')} {_real_text(quantity.find('si:real', _NS))}"
            for quantity in st.findall("dcc:data/dcc:quantity", _NS)
        )
        write(
            "<tr><td>"
            f"{esc(_t(st, 'dcc:name/dcc:content').removeprefix('statement of conformity: '))}"
            "</td>"
            "<td class='verdict "
            f"{esc(verdict)}'>{esc(CONFORMITY_WORDS.get(verdict, 'no statement'))}</td>"
            f"<td>{esc(_t(st, 'dcc:declaration/dcc:content'))} {esc(_t(st, 'dcc:norm'))}</td>"
            f"<td>{esc(figures)}</td></tr>"
        )
    write("</table>")


def _person_rows(adm: ET.Element | None) -> list[tuple[str, str]]:
    """The responsible persons: the main signer who authorised it, and who performed it."""
    rows = []
    for person in adm.findall("dcc:respPersons/dcc:respPerson", _NS) if adm is not None else []:
        main = (
            "Authorised by (main signer)"
            if _t(person, "dcc:mainSigner") == "true"
            else "Performed by"
        )
        rows.append(
            (
                main,
                f"{_t(person, 'dcc:person/dcc:name/dcc:content')}, {_t(person, 'dcc:role')} — "
                + _t(person, "dcc:description/dcc:content"),
            )
        )
    return rows


def _method_rows(results: ET.Element) -> list[tuple[str, str]]:
    """Each method used: its name, with its description, procedure and references."""
    return [
        (
            _t(method, "dcc:name/dcc:content"),
            " ".join(
                filter(
                    None,
                    [
                        _t(method, "dcc:description/dcc:content"),
                        _t(method, "dcc:norm"),
                        "; ".join(
                            (reference.text or "")
                            for reference in method.findall("dcc:reference", _NS)
                        ),
                    ],
                )
            ),
        )
        for method in results.findall("dcc:usedMethods/dcc:usedMethod", _NS)
    ]


def _condition_rows(results: ET.Element) -> list[tuple[str, str]]:
    """Each influence condition: its values, then its description."""
    rows = []
    for condition in results.findall("dcc:influenceConditions/dcc:influenceCondition", _NS):
        reals = "; ".join(
            f"{_t(quantity, 'dcc:name/dcc:content')} {_real_text(quantity.find('si:real', _NS))}"
            for quantity in condition.findall("dcc:data/dcc:quantity", _NS)
        )
        rows.append(
            (
                _t(condition, "dcc:name/dcc:content"),
                f"{reals}. {_t(condition, 'dcc:description/dcc:content')}",
            )
        )
    return rows


def _render_measurement_results(write: Callable[[str], None], results: ET.Element) -> None:
    """The methods, the reference standards, the conditions, then each measurement result."""
    esc = html.escape
    _table(write, "Method", _method_rows(results))
    _render_standards(write, results.findall("dcc:measuringEquipments/dcc:measuringEquipment", _NS))
    _table(write, "Conditions", _condition_rows(results))
    for mr in results.findall("dcc:measurementResult", _NS):
        write(f"<h2>{esc(_t(mr, 'dcc:name/dcc:content'))}</h2>")
        desc = _t(mr, "dcc:description/dcc:content")
        if desc:
            write(f"<p>{esc(desc)}</p>")
        for result in mr.findall("dcc:results/dcc:result", _NS):
            _render_result(write, result)


def _render_statements(write: Callable[[str], None], others: list[ET.Element]) -> None:
    """The certificate's other statements, each a paragraph."""
    declarations = [_t(st, "dcc:declaration/dcc:content") for st in others]
    if declarations:
        write(
            "<h2>Statements</h2>"
            + "".join(f"<p>{html.escape(declaration)}</p>" for declaration in declarations)
        )


def _render_footer(write: Callable[[str], None], root: ET.Element, adm: ET.Element | None) -> None:
    """The software that issued it, and that the XML is the authoritative version."""
    esc = html.escape
    sw = adm.find("dcc:dccSoftware/dcc:software", _NS) if adm is not None else None
    write(
        f"<p class='foot'>Issued by {esc(_t(sw, 'dcc:name/dcc:content'))} "
        f"{esc(_t(sw, 'dcc:release'))} as a DCC {esc(root.get('schemaVersion', ''))} document; "
        "the XML certificate is the authoritative version.</p>"
    )


CONFORMITY_WORDS = {
    "pass": "PASS: conforms",
    "fail": "FAIL: does not conform",
    "conditionalPass": "CONDITIONAL PASS: conforms, the uncertainty reaching beyond the limit",
    "conditionalFail": "CONDITIONAL FAIL: does not conform, the limit within the uncertainty",
}

_CSS = (
    "body{font:11pt/1.4 system-ui,sans-serif;margin:2em auto;max-width:60em;color:#111}"
    "h1{margin:0}.number{font-size:1.3em;margin-top:.2em}h2{margin-top:1.4em;border-bottom:1px "
    "solid #888}"
    "table{border-collapse:collapse;width:100%;margin:.4em 0}th,td{border:1px solid "
    "#bbb;padding:.2em .5em;"
    "text-align:left;vertical-align:top;overflow-wrap:anywhere}"
    "td.n{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap;overflow-wrap:normal}"
    "table.points{font-size:9pt}table.points th{overflow-wrap:normal}"
    "table.verdicts td:nth-child(1){width:9em}table.verdicts td:nth-child(2){width:9em}"
    "table.standards td:nth-child(1){width:13em}table.standards "
    "td:nth-child(2){overflow-wrap:anywhere}"
    "table.standards td:nth-child(3){width:16em}table.standards td:nth-child(4){width:9em}"
    "td,th{overflow-wrap:break-word}"
    "th{background:#eee}.notice{border:2px solid #a00;padding:.4em}.verdict{font-weight:bold}"
    ".fail,.conditionalFail{color:#a00}.pass,.conditionalPass{color:#060}.foot{margin-top:2em;font-size:.9em;color:#444}"
    "@media print{body{margin:0;max-width:none}h2{break-after:avoid}tr{break-inside:avoid}}"
)

_UNIT_TEXT = {
    r"\degree": "°",
    r"\arcsecond": "″",
    r"\arcminute": "′",
    r"\one": "",
    r"\degreecelsius": "°C",
    r"\radian": "rad",
    r"\percent": "%",
}


def _unit_text(unit: str) -> str:
    if unit in _UNIT_TEXT:
        return _UNIT_TEXT[unit]
    return re.sub(r"\\tothe\{(-?\d+)\}", r"^\1", unit).replace("\\", " ").strip()


def _contact_text(c: ET.Element | None) -> str:
    if c is None:
        return ""
    loc = c.find("dcc:location", _NS)
    parts = [
        _t(c, "dcc:name/dcc:content"),
        _t(loc, "dcc:street"),
        f"{_t(loc, 'dcc:postCode')} {_t(loc, 'dcc:city')}".strip(),
        _t(loc, "dcc:countryCode"),
    ]
    return ", ".join(part for part in parts if part)


def _real_text(real: ET.Element | None) -> str:
    if real is None:
        return ""
    unit = _unit_text(_t(real, "si:unit"))
    text = f"{_t(real, 'si:value')} {unit}".strip()
    mu = real.find("si:measurementUncertaintyUnivariate/si:expandedMU", _NS)
    if mu is not None:
        text += (
            f", expanded uncertainty U = {_t(mu, 'si:valueExpandedMU')} {unit} (k = "
            f"{_t(mu, 'si:coverageFactor')}, p = {_t(mu, 'si:coverageProbability')})"
        )
    su = real.find("si:measurementUncertaintyUnivariate/si:standardMU", _NS)
    if su is not None:
        text += f", standard uncertainty u = {_t(su, 'si:valueStandardMU')} {unit}"
    return text


def _table(w: Callable[[str], None], title: str, rows: list[tuple[str, str]]) -> None:
    rows = [(heading, value) for heading, value in rows if value and value.strip(" —")]
    if not rows:
        return
    w(f"<h2>{html.escape(title)}</h2><table>")
    for heading, value in rows:
        w(f"<tr><th>{html.escape(heading)}</th><td>{html.escape(value)}</td></tr>")
    w("</table>")


def _render_standards(w: Callable[[str], None], standards: list[ET.Element]) -> None:
    """The reference standards: identity, their certificate and who issued it, validity and stated
    uncertainty."""
    if not standards:
        return
    esc = html.escape
    w(
        "<h2>Reference standards</h2><table class='standards'><tr><th>Standard</th><th>Its "
        "calibration certificate</th>"
        "<th>Uncertainty its certificate states</th><th>Status</th></tr>"
    )
    for eq in standards:
        cert = eq.find("dcc:certificate", _NS)
        quantities = "; ".join(
            f"{_t(quantity, 'dcc:name/dcc:content')}: {_real_text(quantity.find('si:real', _NS))}"
            for quantity in eq.findall(
                "dcc:measuringEquipmentQuantities/dcc:measuringEquipmentQuantity", _NS
            )
        )
        status = [
            "traceable"
            if _t(cert, "dcc:traceable") == "true"
            else "NOT TRACEABLE: who calibrated it is not named",
            "valid on the day of the calibration"
            if _t(cert, "dcc:inValidityRange") == "true"
            else "NOT VALID on the day of the calibration",
        ]
        ids = "; ".join(
            f"{_t(ident, 'dcc:name/dcc:content')}: {_t(ident, 'dcc:value')}"
            for ident in eq.findall("dcc:identifications/dcc:identification", _NS)
        )
        w(
            f"<tr><td>{esc(_t(eq, 'dcc:name/dcc:content'))}<br>{esc(ids)}</td>"
            f"<td>{esc(_t(cert, 'dcc:referral/dcc:content'))}; SHA-256 "
            f"{esc(_t(cert, 'dcc:value'))}. "
            f"{esc(_t(eq, 'dcc:description/dcc:content'))}</td>"
            f"<td>{esc(quantities or 'not stated as a number')}</td>"
            f"<td>{esc('; '.join(status))}</td></tr>"
        )
    w("</table>")


def _render_result(w: Callable[[str], None], r: ET.Element) -> None:
    """A result: its single values as a table, then every table of points (calibration, validation,
    errors)."""
    esc = html.escape
    w(f"<h3>{esc(_t(r, 'dcc:name/dcc:content'))}</h3>")
    desc = _t(r, "dcc:description/dcc:content")
    if desc:
        w(f"<p>{esc(desc)}</p>")
    for lst in r.findall("dcc:data/dcc:list", _NS):
        quantities = lst.findall("dcc:quantity", _NS)
        if lst.get("refType") != "tiltlab_values":
            _render_table(w, quantities)
        elif any(quantity.find("si:real", _NS) is not None for quantity in quantities):
            _render_values(w, quantities)
        for quantity in quantities:
            if quantity.get("refType") == "tiltlab_parameterVector":
                _render_correlations(w, quantity)


def _render_values(w: Callable[[str], None], quantities: list[ET.Element]) -> None:
    """Single quantities as rows: value, expanded uncertainty and k, standard uncertainty, unit,
    note (columns that no row fills are left out)."""
    esc = html.escape
    mu, su = (
        "si:measurementUncertaintyUnivariate/si:expandedMU/",
        "si:measurementUncertaintyUnivariate/si:standardMU/",
    )
    columns: list[tuple[str, Callable[[ET.Element, ET.Element], str], bool]] = [
        ("Quantity", lambda quantity, real: _t(quantity, "dcc:name/dcc:content"), False),
        ("Value", lambda quantity, real: _t(real, "si:value"), True),
        (
            "Expanded uncertainty U",
            lambda quantity, real: _t(real, mu + "si:valueExpandedMU"),
            True,
        ),
        ("k", lambda quantity, real: _t(real, mu + "si:coverageFactor"), True),
        (
            "Standard uncertainty u",
            lambda quantity, real: _t(real, su + "si:valueStandardMU"),
            True,
        ),
        ("Unit", lambda quantity, real: _unit_text(_t(real, "si:unit")), False),
        ("Note", lambda quantity, real: _t(quantity, "dcc:description/dcc:content"), False),
    ]
    rows = [
        (quantity, real)
        for quantity in quantities
        if (real := quantity.find("si:real", _NS)) is not None
    ]
    used = [
        column for column in columns if any(column[1](quantity, real) for quantity, real in rows)
    ]
    w("<table><tr>" + "".join(f"<th>{esc(heading)}</th>" for heading, _, _ in used) + "</tr>")
    for quantity, real in rows:
        w(
            "<tr>"
            + "".join(
                ("<td class='n'>" if numeric else "<td>") + esc(get(quantity, real)) + "</td>"
                for _, get, numeric in used
            )
            + "</tr>"
        )
    w("</table>")


def _table_columns(quantities: list[ET.Element]) -> list[tuple[str, list[str]]]:
    """Each list quantity's heading and values, followed by its expanded uncertainties and k where
    it has them."""
    cols = []
    for quantity in quantities:
        xl = quantity.find("si:realListXMLList", _NS)
        if xl is None:
            continue
        unit = _unit_text(_t(xl, "si:unitXMLList"))
        mu = "si:measurementUncertaintyUnivariateXMLList/si:expandedMUXMLList/"
        us, ks = (
            _t(xl, mu + "si:valueExpandedMUXMLList").split(),
            _t(xl, mu + "si:coverageFactorXMLList").split(),
        )
        cols.append(
            (
                _t(quantity, "dcc:name/dcc:content") + (f" / {unit}" if unit else ""),
                _t(xl, "si:valueXMLList").split(),
            )
        )
        if us:
            cols.append(
                (f"expanded uncertainty U / {unit}" if unit else "expanded uncertainty U", us)
            )
            cols.append(("k", ks))
    return cols


def _render_table(w: Callable[[str], None], quantities: list[ET.Element]) -> None:
    """Columns of equal length as one table: each quantity's values, then its expanded uncertainty
    and k."""
    esc = html.escape
    cols = _table_columns(quantities)
    if not cols:
        return
    w(
        "<table class='points'><tr><th>#</th>"
        + "".join(f"<th>{esc(heading)}</th>" for heading, _ in cols)
        + "</tr>"
    )
    for i in range(max(len(values) for _, values in cols)):
        w(
            f"<tr><td class='n'>{i + 1}</td>"
            + "".join(
                f"<td class='n'>{esc(values[i] if i < len(values) else '')}</td>"
                for _, values in cols
            )
            + "</tr>"
        )
    w("</table>")


def _covariance_columns(xl: ET.Element | None) -> list[list[float]]:
    """The parameters' covariance matrix, column by column (none without a parameter list)."""
    if xl is None:
        return []
    return [
        [float(value) for value in _t(column, "si:covarianceXMLList/si:valueXMLList").split()]
        for column in xl.findall(
            "si:measurementUncertaintyMultivariateXMLList/si:ellipsoidalRegionMUXMLList/"
            "si:covarianceMatrixXMLList/si:columnXMLList",
            _NS,
        )
    ]


def _render_correlations(w: Callable[[str], None], q: ET.Element) -> None:
    """The parameters' covariance as correlation coefficients (what a reader looks for first)."""
    esc = html.escape
    xl = q.find("si:realListXMLList", _NS)
    labels = _t(xl, "si:labelXMLList").split()
    cols = _covariance_columns(xl)
    if not labels or len(cols) != len(labels):
        return
    sd = [math.sqrt(cols[i][i]) if cols[i][i] > 0 else 0.0 for i in range(len(labels))]
    w(
        "<p>Correlation coefficients of the parameters (the certificate's XML carries their full "
        "covariance matrix):</p>"
    )
    w("<table><tr><th></th>" + "".join(f"<th>{esc(label)}</th>" for label in labels) + "</tr>")
    for i, label in enumerate(labels):
        cells = "".join(
            f"<td class='n'>{cols[j][i] / (sd[i] * sd[j]):+.4f}</td>"
            if sd[i] and sd[j]
            else "<td></td>"
            for j in range(len(labels))
        )
        w(f"<tr><th>{esc(label)}</th>{cells}</tr>")
    w("</table>")
