"""Digital Calibration Certificates: valid DCC 3.3.0 offline, content equal to the record, invalid
ones refused."""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import math
import re
import socket

import numpy as np
import pytest

from service.lims import dcc
from service.lims.content import build_certificate, model_dof
from tests.helpers.certificates import (
    APPROVAL,
    CUSTOMER,
    DEVICE,
    LAB,
    OPERATOR,
    STANDARDS,
    scale_record,
    stage_points,
    stage_record,
)

ORDER = {"lims_order_id": "LIMS-2026-118", "item_serial": "CUST-ITEM-55", "customer": CUSTOMER}


def certificate(record=None, **kw) -> dcc.Certificate:
    record = record or stage_record()
    args = dict(
        number="TL-2026-000007",
        record=record,
        device=DEVICE,
        approval=APPROVAL,
        operator="max",
        operator_person=OPERATOR,
        laboratory=LAB,
        software_version="0.1.0",
        issued_on=dt.date(2026, 11, 22),
        begin_on=dt.date(2026, 11, 20),
        standards=STANDARDS,
        order=ORDER,
        measured_points=stage_points() if record["kind"] == "stage" else (),
        job_id=12,
    )
    args.update(kw)
    return build_certificate(**args)


def decoded(xml: bytes) -> dict:
    """An independent reader: xmlschema's decoder, driven by the schema alone (not by our
    writer)."""
    return dcc.dcc_schema().to_dict(xml.decode())


def _content(d) -> str:
    c = d["dcc:content"]
    c = c[0] if isinstance(c, list) else c
    return c["$"] if isinstance(c, dict) else c


def test_shipped_schemas_are_the_published_files():
    """The README's table of hashes is the contract: an edited schema is noticed."""
    readme = (dcc.SCHEMA_DIR / "README.md").read_text()
    for name in ("dcc.xsd", "SI_Format.xsd", "qudt-quantitykind-shim.xsd"):
        stated = re.search(
            rf"^\| `{re.escape(name)}` .*\| ([0-9a-f]{{64}}) \|$", readme, re.M
        ).group(1)
        assert hashlib.sha256((dcc.SCHEMA_DIR / name).read_bytes()).hexdigest() == stated, name
    assert "GNU LESSER GENERAL PUBLIC LICENSE" in (dcc.SCHEMA_DIR / "COPYING.LESSER").read_text()
    assert "GNU Lesser General Public License" in (dcc.SCHEMA_DIR / "dcc.xsd").read_text()


def test_validation_is_offline(monkeypatch):
    def no_network(*a, **k):
        raise AssertionError("the schema tried to reach the network")

    monkeypatch.setattr(socket, "socket", no_network)
    monkeypatch.setattr(socket, "create_connection", no_network)
    dcc.dcc_schema.cache_clear()
    try:
        xml = dcc.issue(certificate())
        assert dcc.certificate_errors(xml) == []
    finally:
        dcc.dcc_schema.cache_clear()


def test_stage_certificate_is_valid_and_reads_back_equal_to_the_record():
    record = stage_record("kinematic")
    xml = dcc.issue(certificate(record))
    assert dcc.certificate_errors(xml) == []
    doc = decoded(xml)
    adm = doc["dcc:administrativeData"]
    assert doc["@schemaVersion"] == "3.3.0"
    assert adm["dcc:coreData"]["dcc:uniqueIdentifier"] == "TL-2026-000007"
    item = adm["dcc:items"]["dcc:item"][0]
    assert item["dcc:model"] == "SCA126T"
    serials = {
        _content(i["dcc:name"]): i["dcc:value"]
        for i in item["dcc:identifications"]["dcc:identification"]
    }
    # the item by the order's serial and the instrument's own; never a port or role
    assert serials["serial number"] == "CUST-ITEM-55"
    assert serials["serial number reported by the instrument"] == "SN-4711"
    assert item["dcc:installedSoftwares"]["dcc:software"][0]["dcc:release"] == "2.3.1"
    signers = adm["dcc:respPersons"]["dcc:respPerson"]
    main = [p for p in signers if p.get("dcc:mainSigner")]
    assert len(main) == 1 and _content(main[0]["dcc:person"]["dcc:name"]) == APPROVAL.signer.name
    assert _content(adm["dcc:customer"]["dcc:name"]) == CUSTOMER["name"]

    # every parameter of the item with its value and expanded uncertainty, equal to the record's
    # (GUM-rounded); the bench's own parameters (stage scales, desk tilt) are not results of the
    # item
    model = record["model"]
    item_params = {
        n: p for n, p in model["parameters"].items() if n not in model["state"]["chain_parameters"]
    }
    names = model["covariance"]["names"]
    cov = np.asarray(model["covariance"]["matrix"])
    results = doc["dcc:measurementResults"]
    (mr,) = results["dcc:measurementResult"]
    params_result = mr["dcc:results"]["dcc:result"][0]
    quantities = params_result["dcc:data"]["dcc:list"][0]["dcc:quantity"]
    by_label = {q["si:real"]["si:label"]: q["si:real"] for q in quantities}
    assert set(by_label) == set(item_params) and "stage_scale.x" not in by_label
    for name, p in item_params.items():
        real = by_label[name]
        if p.get("fixed"):
            assert "si:measurementUncertaintyUnivariate" not in real
            continue
        mu = real["si:measurementUncertaintyUnivariate"]["si:expandedMU"]
        u = math.sqrt(cov[names.index(name), names.index(name)])
        half_digit = 0.5 * 10 ** (math.floor(math.log10(mu["si:valueExpandedMU"])) - 1) * (1 + 1e-9)
        # the value to U's last decimal place
        assert abs(real["si:value"] - p["value"]) <= half_digit
        assert (
            abs(mu["si:valueExpandedMU"] - mu["si:coverageFactor"] * u)
            <= half_digit + 0.005 * u * 3
        )
        assert mu["si:coverageProbability"] == 0.95
        assert 1.96 <= mu["si:coverageFactor"] < 2.1  # Student's t at the fit's degrees of freedom
        unit = real["si:unit"]
        assert unit == {"deg": r"\degree", "1": r"\one"}[p["unit"]]

    # the validation table: reference, measured, error = measured - reference, with U and k
    table = mr["dcc:results"]["dcc:result"][1]["dcc:data"]["dcc:list"][1]["dcc:quantity"]
    cols = {q["si:realListXMLList"]["si:labelXMLList"][0]: q["si:realListXMLList"] for q in table}
    points = record["validation"]["points"]
    err = cols["error_x_deg"]
    mu = err["si:measurementUncertaintyUnivariateXMLList"]["si:expandedMUXMLList"]
    halves = [
        0.5 * 10 ** (math.floor(math.log10(U)) - 1) * (1 + 1e-9)
        for U in mu["si:valueExpandedMUXMLList"]
    ]
    for i, p in enumerate(points):
        assert (
            abs(cols["reference_x_deg"]["si:valueXMLList"][i] - p["reference_x_deg"]) <= halves[i]
        )
        assert (
            abs(cols["measured_y_deg"]["si:valueXMLList"][i] - p["measured_y_deg"]) <= 2 * halves[i]
        )
        assert (
            abs(err["si:valueXMLList"][i] - (p["measured_x_deg"] - p["reference_x_deg"]))
            <= halves[i]
        )
        assert abs(mu["si:valueExpandedMUXMLList"][i] - p["u_x_deg"]) <= halves[i]
    assert len(mu["si:coverageFactorXMLList"]) == len(points)

    # reference standards with their certificate numbers and hashes; temperature in D-SI
    eq = results["dcc:measuringEquipments"]["dcc:measuringEquipment"]
    assert [
        (e["dcc:certificate"]["dcc:referralID"], e["dcc:certificate"]["dcc:value"]) for e in eq
    ] == [(s["certificate_number"], s["certificate_sha256"]) for s in STANDARDS]
    conditions = {
        " ".join(c["@refType"]): c
        for c in results["dcc:influenceConditions"]["dcc:influenceCondition"]
    }
    # the sensor's own
    cond = conditions["basic_temperature"]["dcc:data"]["dcc:quantity"][0]["si:real"]
    assert (cond["si:value"], cond["si:unit"]) == (20.4, r"\degreecelsius")
    method = results["dcc:usedMethods"]["dcc:usedMethod"][0]
    assert "10.13382/j.jemi.B2407429" in method["dcc:reference"][0]


def test_several_results_and_kinds_are_valid():
    for record in (stage_record("homography"), scale_record()):
        xml = dcc.issue(certificate(record))
        assert dcc.certificate_errors(xml) == []
    two = dataclasses.replace(
        certificate(), results=certificate().results + certificate(scale_record()).results
    )
    xml = dcc.issue(two)
    assert len(decoded(xml)["dcc:measurementResults"]["dcc:measurementResult"]) == 2


def test_substituting_certificate_names_the_one_it_replaces():
    xml = dcc.issue(
        certificate(
            stage_record(version=2, record_id=8), number="TL-2026-000008", replaces="TL-2026-000007"
        )
    )
    ras = decoded(xml)["dcc:administrativeData"]["dcc:coreData"]["dcc:reportAmendedSubstituted"]
    assert ras == {
        "dcc:typeOfChange": "substituted",
        "dcc:replacedUniqueIdentifier": "TL-2026-000007",
    }


def test_in_house_calibration_names_the_lab_as_customer():
    xml = dcc.issue(certificate(order=None))
    assert _content(decoded(xml)["dcc:administrativeData"]["dcc:customer"]["dcc:name"]) == LAB.name


def test_invalid_documents_are_refused():
    good = dcc.issue(certificate())
    for broken in (
        good.replace(b'schemaVersion="3.3.0"', b'schemaVersion="3.2.1"'),
        re.sub(rb"<dcc:uniqueIdentifier>[^<]*</dcc:uniqueIdentifier>", b"", good),
        good.replace(b"<si:coverageProbability>0.95<", b"<si:coverageProbability>95<"),
        good.replace(b"<dcc:countryCode>DE<", b"<dcc:countryCode>Germany<"),
        good[: len(good) // 2],
    ):
        assert dcc.certificate_errors(broken)
        with pytest.raises(dcc.InvalidCertificate):
            dcc.validate(broken)


def test_content_that_would_make_an_invalid_certificate_is_never_issued():
    bad_country = dataclasses.replace(certificate(), country_code="Germany")
    with pytest.raises(dcc.InvalidCertificate, match="countryCodeISO3166_1"):
        dcc.issue(bad_country)
    with pytest.raises(dcc.InvalidCertificate, match="main signer"):
        dcc.issue(dataclasses.replace(certificate(), persons=()))
    with pytest.raises(dcc.InvalidCertificate, match="no D-SI equivalent"):
        dcc.dsi_unit("furlong")
    value = certificate().results[0].results[0].values[0]
    nan = dataclasses.replace(value, value=float("nan"))
    res = dataclasses.replace(certificate().results[0].results[0], values=(nan,))
    with pytest.raises(dcc.InvalidCertificate, match="not a finite number"):
        dcc.issue(dataclasses.replace(certificate(), results=(dcc.MeasurementResult("x", (res,)),)))


def test_dsi_units():
    assert dcc.dsi_unit("deg") == r"\degree"
    assert dcc.dsi_unit("1/deg") == r"\degree\tothe{-1}"
    assert dcc.dsi_unit("arcsec/count^2") == r"\arcsecond"
    assert dcc.dsi_unit("reading/arcsec") == r"\arcsecond\tothe{-1}"
    assert dcc.dsi_unit("1") == r"\one"


def test_model_dof_takes_the_smallest_stated():
    assert model_dof({"fit": {"chain": {"dof": 153}, "meas": {"dof": 154}}}) == 153
    assert model_dof({"fit": {"dof": 8}, "state": {"meas_dof": 12}}) == 8
    assert model_dof({"fit": {}}) == math.inf


def test_html_rendering_shows_what_the_xml_says():
    record = stage_record()
    xml = dcc.issue(certificate(record, replaces="TL-2026-000001"))
    page = dcc.render_html(xml)
    assert "TL-2026-000007" in page and "SN-4711" in page and "SCA126T" in page and "2.3.1" in page
    assert "substitutes certificate TL-2026-000001" in page
    assert APPROVAL.signer.name in page and "DAkkS-2026-0412" in page and "@media print" in page
    # a parameter as people read it: U to two significant digits, the value to the same place
    name = record["model"]["covariance"]["names"][0]
    assert re.search(
        rf"<td>{re.escape(name)}</td><td class='n'>-?\d+\.\d+</td><td class='n'>0\.0*[1-9]\d</td>",
        page,
    )
    assert page.count("<tr>") > len(record["model"]["parameters"]) + len(
        record["validation"]["points"]
    )


def test_a_reviewer_finds_what_an_unreviewed_certificate_had():
    """The checks every issued certificate passes (tests/helpers/reviewer.py) catch each finding of
    a review."""
    from tests.helpers.reviewer import problems

    good = dcc.issue(certificate(stage_record("kinematic")))
    assert problems(good) == []
    text = good.decode()
    assert (
        "\\degreecelsius" in text and "student-t" in text and "<si:covarianceMatrixXMLList>" in text
    )
    assert (
        "CUST-ITEM-55" in text
        and 'refType="tiltlab_modelParameter"' in text
        and "<dcc:refTypeDefinition " in text
    )
    u = re.search(r"<si:valueExpandedMU>([^<]+)<", text).group(1)
    for bad, finding in (
        (text.replace("\\degreecelsius", "\\degreeCelsius"), "not valid D-SI"),
        (
            text.replace(f"<si:valueExpandedMU>{u}<", f"<si:valueExpandedMU>{u}7<", 1),
            "not GUM-rounded",
        ),
        # a parameter's value, beside its U
        (
            text[: (at := text.index('<dcc:quantity refType="tiltlab_modelParameter"'))]
            + re.sub(
                r"<si:value>([^<]+)</si:value>",
                r"<si:value>0.6126699999999999</si:value>",
                text[at:],
                count=1,
            ),
            "GUM-rounded",
        ),
        (
            re.sub(
                r"<si:measurementUncertaintyMultivariateXMLList>.*?</si:measurementUncertaintyMultivariateXMLList>",
                "",
                text,
                flags=re.S,
            ),
            "no covariance",
        ),
        (
            text.replace("<dcc:value>CUST-ITEM-55<", "<dcc:value>address 0x00 on /dev/pts/3<"),
            "a port or role",
        ),
        (
            re.sub(
                r"<dcc:refTypeDefinition "
                r'refType="tiltlab_modelParameter">.*?</dcc:refTypeDefinition>',
                "",
                text,
                flags=re.S,
            ),
            "without a definition",
        ),
    ):
        found = problems(bad.encode())
        assert any(finding in f for f in found), (finding, found)
