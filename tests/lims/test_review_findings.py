"""What an accredited laboratory's reviewer queried in a certificate, point by point (ISO/IEC 17025
7.8, the DCC's vocabulary): each check reads the issued XML (or its printable page) as the reviewer
would."""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
import re
import xml.etree.ElementTree as ET
from typing import cast

import numpy as np
import pytest

from service.calibration.budget import combine, record_budget
from service.calibration.model import CalibrationModel, ModelState
from service.calibration.registry import get_method
from service.calibration.uncertainty import coverage_factor, welch_satterthwaite
from service.lims import dcc
from service.lims.content import CertificateRefused, build_certificate
from service.scenarios import load_scenario
from service.scenarios.run import run_scenario
from tests.helpers.certificates import (
    APPROVAL,
    CUSTOMER,
    DEVICE,
    LAB,
    OPERATOR,
    STANDARDS,
    _stage_fit,
    stage_points,
    stage_record,
)

NS = {"dcc": dcc.DCC_NS, "si": dcc.SI_NS}
SI = "{" + dcc.SI_NS + "}"
ORDER = {"lims_order_id": "LIMS-2026-118", "item_serial": "CUST-ITEM-55", "customer": CUSTOMER}


def _budget(model_json: dict) -> dict:
    """The budget a record of this model keeps: the reference standard, both sensors' resolution,
    the fit."""
    model = CalibrationModel.from_json_dict(model_json)
    return record_budget(
        parameters=model_json["parameters"],
        parameter_u={n: s for n in model.parameters if (s := model.std(n)) is not None},
        dof_fit=154.0,
        standards=[
            {
                "name": "reference inclinometer",
                "serial": "REF-77",
                "certificate_id": "DAkkS-2026-0412",
                "expanded_uncertainty_deg": 0.001,
                "coverage_factor": 2.0,
            }
        ],
        resolutions_deg={"measurement sensor": 1e-4, "reference sensor": 1e-4},
        tilt_u_fit_deg=(1.5e-3, 1.4e-3),
        tilt_dof_fit=(154.0, 154.0),
    )


def _record(method: str = "kinematic", **changes: object) -> dict:
    record = stage_record(method)
    return {**record, "budget": _budget(record["model"]), **changes}


def _issue(record: dict | None = None, **kw: object) -> bytes:
    args: dict = dict(
        number="TL-2026-000007",
        record=record or _record(),
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
        measured_points=stage_points(),
        job_id=12,
    )
    args.update(kw)
    return dcc.issue(build_certificate(**args))  # signed and reviewed (tests/lims/conftest.py)


def _result(root: ET.Element, name: str) -> ET.Element:
    found = [
        r
        for r in root.iter(f"{{{dcc.DCC_NS}}}result")
        if r.findtext("dcc:name/dcc:content", "", NS) == name
    ]
    assert len(found) == 1, name
    return found[0]


# 1. Labels: software reads a quantity by its label


def test_1_every_label_in_a_list_is_unique_the_budget_s_two_resolutions_included() -> None:
    root = ET.fromstring(_issue())
    for lst in root.iter(f"{{{dcc.DCC_NS}}}list"):
        labels = [e.text for e in lst.iter(SI + "label")] + [
            e.text for e in lst.iter(SI + "labelXMLList")
        ]
        assert len(labels) == len(set(labels)), [x for x in labels if labels.count(x) > 1]
    budget = _result(root, "Uncertainty budget")
    labels = {e.text for e in budget.iter(SI + "label")}
    assert {
        "standard_uncertainty_tilt_x_deg_resolution_measurement_sensor_resolution",
        "standard_uncertainty_tilt_x_deg_resolution_reference_sensor_resolution",
        "standard_uncertainty_tilt_x_deg_fit",
        "standard_uncertainty_tilt_x_deg_reference_standard",
        "combined_standard_uncertainty_tilt_x_deg",
        "coverage_factor_tilt_x_deg",
        "expanded_uncertainty_tilt_x_deg",
    } <= labels
    # every name in the budget says which uncertainty it is
    for q in budget.iter(f"{{{dcc.DCC_NS}}}quantity"):
        name = q.findtext("dcc:name/dcc:content", "", NS)
        assert (
            "standard uncertainty" in name
            or "expanded uncertainty" in name
            or "coverage factor" in name
        ), name
    # and the writer refuses a list that would repeat one
    content = build_certificate(
        number="TL-1",
        record=_record(),
        device=DEVICE,
        approval=APPROVAL,
        operator="max",
        operator_person=OPERATOR,
        laboratory=LAB,
        software_version="0",
        standards=STANDARDS,
        issued_on=dt.date(2026, 11, 22),
        begin_on=dt.date(2026, 11, 20),
    )
    params = content.results[0].results[0]
    twice = dataclasses.replace(params, values=params.values + params.values[:1])
    with pytest.raises(dcc.InvalidCertificate, match="more than once"):
        dcc.issue(dataclasses.replace(content, results=(dcc.MeasurementResult("x", (twice,)),)))


# 2. The person authorising the certificate: a name and a function


def test_2_the_main_signer_is_a_person_with_a_function_and_the_operator_is_named_too() -> None:
    root = ET.fromstring(_issue())
    persons = root.findall("dcc:administrativeData/dcc:respPersons/dcc:respPerson", NS)
    main = [p for p in persons if p.findtext("dcc:mainSigner", "", NS) == "true"]
    assert len(main) == 1
    assert main[0].findtext("dcc:person/dcc:name/dcc:content", "", NS) == "Dr. Erika Mustermann"
    assert main[0].findtext("dcc:role", "", NS) == "Head of Laboratory"
    operator = [p for p in persons if p.findtext("dcc:mainSigner", "", NS) == "false"]
    assert operator[0].findtext("dcc:person/dcc:name/dcc:content", "", NS) == "Max Muster"
    assert operator[0].findtext("dcc:role", "", NS) == "Calibration Technician"
    assert "job 12" in operator[0].findtext("dcc:description/dcc:content", "", NS)
    with pytest.raises(CertificateRefused, match="names no person"):
        _issue(approval=dataclasses.replace(APPROVAL, signer=None))
    with pytest.raises(CertificateRefused, match="function was not recorded"):
        _issue(
            approval=dataclasses.replace(
                APPROVAL, signer=dataclasses.replace(APPROVAL.signer, function=None)
            )
        )


# 3. The reference standard: its U, k and p as numbers, and who calibrated it


def test_3_the_standard_s_uncertainty_and_calibration_laboratory_are_stated() -> None:
    root = ET.fromstring(_issue())
    eq = root.findall("dcc:measurementResults/dcc:measuringEquipments/dcc:measuringEquipment", NS)[
        0
    ]
    quantities = {
        q.findtext("si:real/si:label", "", NS): q.find("si:real", NS)
        for q in eq.findall("dcc:measuringEquipmentQuantities/dcc:measuringEquipmentQuantity", NS)
    }
    assert (
        float(quantities["expanded_uncertainty_of_the_standard"].findtext("si:value", "", NS))
        == 0.001
    )
    assert (
        quantities["expanded_uncertainty_of_the_standard"].findtext("si:unit", "", NS) == r"\degree"
    )
    assert float(quantities["coverage_factor_of_the_standard"].findtext("si:value", "", NS)) == 2.0
    assert (
        float(quantities["coverage_probability_of_the_standard"].findtext("si:value", "", NS))
        == 0.95
    )
    assert (
        float(quantities["standard_uncertainty_of_the_standard"].findtext("si:value", "", NS))
        == 0.0005
    )
    cert = eq.find("dcc:certificate", NS)
    assert (
        cert.findtext("dcc:traceable", "", NS) == "true"
        and cert.findtext("dcc:inValidityRange", "", NS) == "true"
    )
    assert (
        "issued by Angle Calibration Laboratory AG (Hamburg, DE), accreditation D-K-12345-01-00"
        in cert.findtext("dcc:referral/dcc:content", "", NS)
    )
    ids = {
        i.findtext("dcc:value", "", NS): i.findtext("dcc:issuer", "", NS)
        for i in eq.findall("dcc:identifications/dcc:identification", NS)
    }
    assert ids == {
        "REF-77": "manufacturer",
        "DAkkS-2026-0412": "calibrationLaboratory",
        "D-K-12345-01-00": "calibrationLaboratory",
    }


# 4. The laboratory's ambient conditions with their uncertainty


def test_4_ambient_temperature_and_humidity_are_stated_with_their_standard_uncertainty() -> None:
    root = ET.fromstring(_issue())
    conditions = {
        c.get("refType"): c
        for c in root.findall(
            "dcc:measurementResults/dcc:influenceConditions/dcc:influenceCondition", NS
        )
    }
    air = conditions["basic_temperature tiltlab_ambientCondition"]
    assert (
        air.findtext("dcc:name/dcc:content", "", NS) == "ambient air temperature of the laboratory"
    )
    real = air.find("dcc:data/dcc:quantity/si:real", NS)
    assert (real.findtext("si:value", "", NS), real.findtext("si:unit", "", NS)) == (
        "20.30",
        r"\degreecelsius",
    )
    assert (
        real.findtext(
            "si:measurementUncertaintyUnivariate/si:standardMU/si:valueStandardMU", "", NS
        )
        == "0.10"
    )
    humidity = conditions["basic_humidity tiltlab_ambientCondition"].find(
        "dcc:data/dcc:quantity/si:real", NS
    )
    assert humidity.findtext("si:unit", "", NS) == r"\percent"
    assert (
        humidity.findtext(
            "si:measurementUncertaintyUnivariate/si:standardMU/si:valueStandardMU", "", NS
        )
        == "2.0"
    )
    # the sensor's own temperature stays, named for what it is
    assert "internal temperature" in conditions["basic_temperature"].findtext(
        "dcc:name/dcc:content", "", NS
    )


# 5. Which U holds for what: a mean of the readings of a point, or a single reading


def test_5_the_budget_says_its_U_holds_for_a_mean_and_states_a_single_reading_s_too() -> None:
    budget = _result(ET.fromstring(_issue()), "Uncertainty budget")
    assert "holds for a corrected value that is the mean of 10 readings" in budget.findtext(
        "dcc:description/dcc:content", "", NS
    )
    values = {
        q.findtext("si:real/si:label", "", NS): float(q.findtext("si:real/si:value", "", NS))
        for q in budget.iter(f"{{{dcc.DCC_NS}}}quantity")
    }
    mean, single = (
        values["expanded_uncertainty_tilt_x_deg"],
        values["expanded_uncertainty_tilt_x_deg_single_reading"],
    )
    # a single reading adds its noise beyond that of the mean of ten: s²(1 - 1/10), s = 0.001 deg
    # (the scenario's)
    u_c = values["combined_standard_uncertainty_tilt_x_deg"]
    assert single > mean
    assert single == pytest.approx(
        float(coverage_factor(1e9)) * math.sqrt(u_c**2 + 1e-6 * 0.9), rel=0.05
    )


# 6. The reference values at the calibration points carry their uncertainty


def test_6_reference_values_at_the_calibration_points_have_an_expanded_uncertainty() -> None:
    points = _result(ET.fromstring(_issue()), "Calibrated range and calibration points")
    columns = {
        q.findtext("si:realListXMLList/si:labelXMLList", "", NS): q.find("si:realListXMLList", NS)
        for q in points.iter(f"{{{dcc.DCC_NS}}}quantity")
        if q.find("si:realListXMLList", NS) is not None
    }
    for axis in ("x", "y"):
        ref = columns[f"reference_{axis}_deg"]
        U = [
            float(v)
            for v in ref.findtext(
                "si:measurementUncertaintyUnivariateXMLList/si:expandedMUXMLList/"
                "si:valueExpandedMUXMLList",
                "",
                NS,
            ).split()
        ]
        assert len(U) == len(ref.findtext("si:valueXMLList", "", NS).split()) == 81
        # at least the standard's own U (0.001 deg, k = 2), with the reference sensor's resolution
        # and noise
        assert all(0.001 <= x < 0.002 for x in U), U[:3]


# 7. The covariance matrix is exactly symmetric


def test_7_the_covariance_matrix_is_exactly_symmetric_even_from_an_asymmetric_model_file() -> None:
    record = _record()
    cov = record["model"]["covariance"]
    matrix = np.asarray(cov["matrix"], dtype=float)
    # a correlated pair (zero offset, mounting tilt): the file's halves differ in their last digits
    i, j = 0, 4
    matrix[i, j] *= 1 + 1.4e-4
    model = {**record["model"], "covariance": {**cov, "matrix": matrix.tolist()}}
    root = ET.fromstring(_issue({**record, "model": model}))
    columns = [
        c.findtext("si:covarianceXMLList/si:valueXMLList", "", NS).split()
        for c in root.iter(SI + "columnXMLList")
    ]
    n = len(columns)
    assert n >= 6
    assert all(columns[a][b] == columns[b][a] for a in range(n) for b in range(n))


# 8. Welch-Satterthwaite over components resting on one estimated σ


def test_8_components_resting_on_one_fit_s_sigma_keep_that_fit_s_degrees_of_freedom() -> None:
    parts = [(np.array([2e-6]), 154.0), (np.array([1.5e-6]), 154.0), (np.array([0.8e-6]), 154.0)]
    # not 154·(Σv)²/Σv² ≈ 342
    assert float(welch_satterthwaite(parts)[0]) == pytest.approx(154.0, rel=1e-12)
    # independent estimates still combine: a second fit's component with its own ν
    mixed = float(welch_satterthwaite(parts[:2] + [(np.array([1e-6]), 20.0)])[0])
    assert mixed == pytest.approx(
        (3.5e-6 + 1e-6) ** 2 / (3.5e-6**2 / 154 + 1e-6**2 / 20), rel=1e-12
    )
    run = run_scenario(load_scenario("seed000"), seed=3)
    # the axis transform's parameters rest on the scatter about its uncorrected bias (162 rows, two
    # angles and two means: ν = 158); one reading's noise is its own estimate (the three-way
    # comparison, with its own ν): two estimates, so the random part's k lies between the normal's
    # and Student's t at the fewer; the bias then widens U beyond |b| (k on √(b² + u²))
    model = CalibrationModel.from_json_dict(_stage_fit("axis-transform", 3)[0])
    nu = float(model.state["meas_dof"])
    assert nu == 158.0
    fewest = min(nu, float(model.state["meas_reading_dof"]))
    random_only = CalibrationModel.from_json_dict(_stage_fit("axis-transform", 3)[0])
    random_only.state = cast(
        ModelState,
        {k: v for k, v in model.state.items() if k != "meas_uncorrected_bias_deg"},
    )
    out = get_method("stage", "axis-transform").correct(random_only, run.columns)
    for k in (out["k_tilt_x"], out["k_tilt_y"]):
        assert np.all(
            (k >= float(coverage_factor(np.inf))) & (k <= float(coverage_factor(fewest)) + 1e-12)
        ), k
    biased = get_method("stage", "axis-transform").correct(model, run.columns)
    for axis, bias in zip("xy", model.state["meas_uncorrected_bias_deg"], strict=True):
        assert np.all(biased[f"u_tilt_{axis}_deg"] > abs(bias))
    # the kinematic measurement fit gives each axis its own variance (81 points, 8 parameters: 77
    # degrees of freedom each) for its parameters' part; one reading's noise is its own estimate
    # (the three-way comparison, with its own ν): two estimates, combined by Welch-Satterthwaite
    # (whose ν may exceed either's), so k is at most Student's t at the fewer and at least the
    # normal's 1.96
    model = CalibrationModel.from_json_dict(_stage_fit("kinematic", 3)[0])
    out = get_method("stage", "kinematic").correct(model, run.columns)
    assert float(model.state["meas_dof"]) == 77.0 and model.fit["meas"]["dof"] == 154
    fewest = min(77.0, float(model.state["meas_reading_dof"]))
    for k in (out["k_tilt_x"], out["k_tilt_y"]):
        assert np.all(
            (k >= float(coverage_factor(np.inf))) & (k <= float(coverage_factor(fewest)) + 1e-12)
        ), k
    # and a budget combining that fit part with the independent standard and resolutions has its WS
    # ν
    c = combine(np.array([1.5e-3]), np.array([154.0]), [])
    assert float(c.dof_eff[0]) == pytest.approx(154.0)


# 9. The printable page shows what the XML holds for people


def test_9_the_printable_page_shows_points_validation_budget_conditions_and_statements() -> None:
    xml = _issue()
    page = dcc.render_html(xml)
    tables = re.findall(r"<table class='points'>(.*?)</table>", page, flags=re.S)
    rows = [t.count("<tr>") - 1 for t in tables]
    validation = len(stage_record()["validation"]["points"])
    assert validation in rows  # the validation table
    assert 81 in rows  # the calibration points
    assert 81 + 9 in rows  # the indication errors at every point
    assert "reference x / °" in page and "expanded uncertainty U / °" in page
    assert (
        "ambient air temperature of the laboratory" in page
        and "standard uncertainty u = 0.10 °C" in page
    )
    assert (
        "Uncertainty budget" in page
        and "holds for a corrected value that is the mean of 10 readings" in page
    )
    assert "Dr. Erika Mustermann, Head of Laboratory" in page
    assert (
        "Angle Calibration Laboratory AG" in page
        and "expanded uncertainty U of the standard" in page
    )


# 11. No certificate for a result that is not traceable


def test_11_no_certificate_without_a_valid_registered_standard_naming_who_calibrated_it() -> None:
    with pytest.raises(CertificateRefused, match="no reference standard: not traceable"):
        _issue(standards=[])
    with pytest.raises(CertificateRefused, match="does not name the laboratory that calibrated it"):
        _issue(standards=[{k: v for k, v in STANDARDS[0].items() if k != "calibrated_by"}])
    with pytest.raises(CertificateRefused, match="was not valid on 2027-02-01"):
        _issue(standards=STANDARDS[:1], begin_on=dt.date(2027, 2, 1))
    with pytest.raises(CertificateRefused, match="states its uncertainty as a number"):
        # a thermometer: no angle uncertainty to carry the result's scale
        _issue(standards=STANDARDS[1:])
