"""Statements of conformity by the ILAC-G8 decision rules: results placed on purpose inside, near
and outside the limit give the statement the rule gives, in the decision itself, in the
certificate's XML (schema-valid, signed and checked by xmllint and xmlsec1) and in its printable
page; the probability of false acceptance is that of the error's distribution."""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from scipy import stats

from service.calibration.budget import standard_component
from service.lims import dcc
from service.lims.as_found import MeasuredPoint, as_found
from service.lims.conformity import (
    Conformity,
    PointError,
    decide,
    false_acceptance_probability,
    point_conformity,
)
from service.lims.content import build_certificate
from service.storage.specification import DecisionRule, SpecificationProblem, specification_of
from tests.helpers.certificates import APPROVAL, DEVICE, LAB, OPERATOR, STANDARDS, stage_record
from tests.helpers.external_checks import xmllint_errors, xmlsec1_verifies

NS = {"dcc": dcc.DCC_NS, "si": dcc.SI_NS}
MPE = 0.05
U = 0.004
# |e| + U below the limit, straddling it from inside (|e| <= MPE < |e| + U), from outside (|e| - U
# <= MPE < |e|), and |e| - U above it
PLACES = {
    "inside": MPE - 2 * U,
    "near_inside": MPE - U / 2,
    "near_outside": MPE + U / 2,
    "outside": MPE + 2 * U,
}
EXPECTED = {
    "simple_acceptance": {
        "inside": "pass",
        "near_inside": "pass",
        "near_outside": "fail",
        "outside": "fail",
    },
    "guarded_acceptance": {
        "inside": "pass",
        "near_inside": "fail",
        "near_outside": "fail",
        "outside": "fail",
    },
    "non_binary": {
        "inside": "pass",
        "near_inside": "conditionalPass",
        "near_outside": "conditionalFail",
        "outside": "fail",
    },
}


def _points(worst: float) -> list[PointError]:
    """Five points: four well inside, one (the third) at `worst`, of either sign."""
    return [PointError(e, U, 2.0, 60.0) for e in (0.001, -0.01, worst, 0.02, -0.005)]


@pytest.mark.parametrize("rule", list(EXPECTED))
@pytest.mark.parametrize("place", list(PLACES))
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_each_rule_gives_the_statement_ilac_g8_gives(rule: str, place: str, sign: float) -> None:
    d = decide(_points(sign * PLACES[place]), MPE, DecisionRule(rule))
    assert d.conformity.value == EXPECTED[rule][place]
    assert d.worst_index == 2 and d.worst_error == sign * PLACES[place] and d.n_points == 5


def test_guard_band_as_a_stated_fraction_of_U() -> None:
    # passes with w = U/4, fails with w = U (and with w = U/2 only at equality)
    near = _points(MPE - U / 2)
    assert decide(near, MPE, DecisionRule.GUARDED_ACCEPTANCE, 0.25).conformity is Conformity.PASS
    assert decide(near, MPE, DecisionRule.GUARDED_ACCEPTANCE, 1.0).conformity is Conformity.FAIL
    assert (
        point_conformity(PointError(MPE - U / 2, U, 2.0), MPE, DecisionRule.GUARDED_ACCEPTANCE, 0.5)
        is Conformity.PASS
    )


def test_the_worst_point_decides_and_one_failing_point_fails_the_quantity() -> None:
    mixed = [PointError(e, U, 2.0) for e in (MPE - U / 2, MPE + 2 * U, 0.0)]
    d = decide(mixed, MPE, DecisionRule.NON_BINARY)
    assert d.conformity is Conformity.FAIL and d.worst_index == 1


def test_probability_of_false_acceptance_is_that_of_the_errors_t_distribution() -> None:
    """The probability that the true error lies beyond ±MPE, from Student's t at the error's degrees
    of freedom (scipy.stats, independently), and the largest over the points that pass."""
    for e, U_, k, nu in (
        (0.04, 0.01, 2.0, 60.0),
        (-0.049, 0.004, 2.2, 12.0),
        (0.0, 0.05, 1.96, math.inf),
    ):
        u = U_ / k
        dist = stats.t(nu, loc=e, scale=u) if math.isfinite(nu) else stats.norm(loc=e, scale=u)
        expected = dist.cdf(-MPE) + dist.sf(MPE)
        assert false_acceptance_probability(PointError(e, U_, k, nu), MPE) == pytest.approx(
            expected, rel=1e-9
        )
    d = decide(_points(MPE - U / 2), MPE, DecisionRule.SIMPLE_ACCEPTANCE)
    assert d.largest_false_acceptance == pytest.approx(
        stats.t(60.0, loc=MPE - U / 2, scale=U / 2).sf(MPE), rel=1e-9
    )
    # accepting |e| one u inside the limit risks one in six (ILAC-G8 4.2.1)
    assert d.largest_false_acceptance > 0.15
    assert (
        decide(_points(MPE + 2 * U), MPE, DecisionRule.SIMPLE_ACCEPTANCE).largest_false_acceptance
        is not None
    )
    assert (
        decide(
            [PointError(MPE + U, U, 2.0)], MPE, DecisionRule.SIMPLE_ACCEPTANCE
        ).largest_false_acceptance
        is None
    )


def test_the_probability_of_false_acceptance_covers_simulated_items() -> None:
    """Items whose true errors are known: measured with the stated U, accepted by simple acceptance;
    the share of accepted items whose true error lies beyond the limit is the mean stated
    probability of false acceptance."""
    rng = np.random.default_rng(2024)
    u, nu = 0.003, math.inf
    true = rng.uniform(MPE - 8 * u, MPE + 8 * u, 40_000)
    measured = true + rng.normal(0.0, u, true.size)
    accepted = np.abs(measured) <= MPE
    # a flat prior over the true errors near the limit: the stated probability is the posterior's
    stated = np.array(
        [
            false_acceptance_probability(PointError(float(m), 2 * u, 2.0, nu), MPE)
            for m in measured[accepted]
        ]
    )
    actual = np.abs(true[accepted]) > MPE
    n = int(accepted.sum())
    tolerance = 5 * math.sqrt(stated.mean() * (1 - stated.mean()) / n)
    assert abs(actual.mean() - stated.mean()) < tolerance, (actual.mean(), stated.mean(), n)


def test_specifications_are_checked_naming_the_field() -> None:
    good = specification_of(
        {
            "max_permissible_error_deg": 0.05,
            "decision_rule": "guarded_acceptance",
            "guard_band_fraction": 0.5,
            "parameters": {"zero_offset.meas_x_deg": {"nominal": 0, "max_permissible_error": 0.02}},
        }
    )
    assert (
        good is not None
        and good.guard_band_fraction == 0.5
        and good.parameters[0].max_permissible_error == 0.02
    )
    for bad, field in (
        (
            {"max_permissible_error_deg": 0, "decision_rule": "simple_acceptance"},
            "specification.max_permissible_error_deg",
        ),
        (
            {"max_permissible_error_deg": 0.05, "decision_rule": "lenient"},
            "specification.decision_rule",
        ),
        (
            {
                "max_permissible_error_deg": 0.05,
                "decision_rule": "non_binary",
                "guard_band_fraction": 0.5,
            },
            "specification.guard_band_fraction",
        ),
        (
            {"max_permissible_error_deg": 0.05, "decision_rule": "non_binary", "tolerance": 1},
            "specification.tolerance",
        ),
        (
            {
                "max_permissible_error_deg": 0.05,
                "decision_rule": "non_binary",
                "parameters": {"zero offset": {}},
            },
            "specification.parameters.zero offset",
        ),
    ):
        with pytest.raises(SpecificationProblem) as exc:
            specification_of(bad)
        assert exc.value.field == field, (bad, str(exc.value))


# ---------------------------------------------------------------- the certificate's statements


REF_STD = standard_component("reference inclinometer", 0.001, 2.0)
RESOLUTION = 0.0001


def _placed_points(x_error: float, y_error: float) -> list[MeasuredPoint]:
    """Twelve points of a job (nine fitted, three validation) whose x error at point 4 and y error
    at point 10 are the given ones in units of those points' own U (the rest well inside)."""
    rng = np.random.default_rng(5)
    refs = [(float(a), float(b)) for a, b in rng.uniform(-10, 10, (12, 2))]
    base = [
        MeasuredPoint(i, i < 9, r, r, (0.0004, 0.0004), (0.0004, 0.0004), 10, 10)
        for i, r in enumerate(refs)
    ]
    found = as_found(base, [REF_STD], RESOLUTION, RESOLUTION)
    U_x, U_y = found["x"].error.expanded_u, found["y"].error.expanded_u
    out = []
    for i, r in enumerate(refs):
        ex = MPE + x_error * U_x[i] if i == 4 else 0.01 * (-1) ** i
        ey = -(MPE + y_error * U_y[i]) if i == 10 else 0.005 * (-1) ** i
        out.append(dataclasses.replace(base[i], indication_deg=(r[0] + ex, r[1] + ey)))
    return out


OFFSETS = {"inside": -2.0, "near_inside": -0.5, "near_outside": 0.5, "outside": 2.0}


def _certificate(rule: str, x_place: str, y_place: str) -> bytes:
    spec = specification_of({"max_permissible_error_deg": MPE, "decision_rule": rule})
    content = build_certificate(
        number="TL-2026-000031",
        record=stage_record("homography"),
        device=DEVICE,
        approval=APPROVAL,
        operator="max",
        operator_person=OPERATOR,
        laboratory=LAB,
        software_version="0.1.0",
        issued_on=dt.date(2026, 11, 22),
        begin_on=dt.date(2026, 11, 20),
        standards=STANDARDS[:1],
        job_id=3,
        order={
            "lims_order_id": "LIMS-31",
            "item_serial": "CUST-31",
            "customer": {"name": "Survey Ltd", "city": "Berlin", "country_code": "DE"},
        },
        measured_points=_placed_points(OFFSETS[x_place], OFFSETS[y_place]),
        specification=spec,
    )
    return dcc.issue(content)  # signed and reviewed (tests/lims/conftest.py)


@pytest.mark.parametrize("rule", list(EXPECTED))
def test_certificates_state_each_rules_statement_in_xml_and_html(
    rule: str, lab_signing_files
) -> None:  # type: ignore[no-untyped-def]
    for x_place, y_place in (("inside", "near_inside"), ("near_outside", "outside")):
        xml = _certificate(rule, x_place, y_place)
        root = ET.fromstring(xml)
        statements = {
            s.findtext("dcc:name/dcc:content", "", NS): s
            for s in root.findall("dcc:administrativeData/dcc:statements/dcc:statement", NS)
        }
        x = statements["statement of conformity: indication error, x axis"]
        y = statements["statement of conformity: indication error, y axis"]
        assert x.findtext("dcc:conformity", "", NS) == EXPECTED[rule][x_place]
        assert y.findtext("dcc:conformity", "", NS) == EXPECTED[rule][y_place]
        assert x.findtext("dcc:norm", "", NS) == "ILAC-G8:09/2019" and rule.split("_")[
            0
        ] in x.findtext("dcc:declaration/dcc:content", "", NS).replace("-", "_")
        mpe = [
            q
            for q in x.iter(f"{{{dcc.SI_NS}}}real")
            if q.findtext("si:label", "", NS) == "max_permissible_error"
        ]
        assert float(mpe[0].findtext("si:value", "", NS)) == MPE
        if rule == "simple_acceptance" and EXPECTED[rule][x_place] == "pass":
            assert "largest probability of false acceptance" in x.findtext(
                "dcc:declaration/dcc:content", "", NS
            )
        # the indication errors the statements rest on, with their U
        table = [
            q
            for q in root.iter(f"{{{dcc.DCC_NS}}}quantity")
            if q.get("refType") == "tiltlab_indicationError"
        ]
        assert {q.findtext("si:realListXMLList/si:labelXMLList", "", NS) for q in table} >= {
            "indication_error_x_deg",
            "indication_error_y_deg",
        }
        assert xmllint_errors(xml) == []
        assert xmlsec1_verifies(xml, lab_signing_files[1])
        page = dcc.render_html(xml)
        words = {
            "pass": "PASS: conforms",
            "fail": "FAIL: does not conform",
            "conditionalPass": "CONDITIONAL PASS",
            "conditionalFail": "CONDITIONAL FAIL",
        }
        assert "Statements of conformity" in page
        assert words[EXPECTED[rule][x_place]] in page and words[EXPECTED[rule][y_place]] in page


def test_named_parameters_are_stated_on_with_their_U() -> None:
    spec = specification_of(
        {
            "max_permissible_error_deg": 1.0,
            "decision_rule": "non_binary",
            "parameters": {
                "zero_offset.meas_x_deg": {"nominal": 0.0, "max_permissible_error": 0.5},
                "no_such_parameter": {"max_permissible_error": 1.0},
            },
        }
    )
    content = build_certificate(
        number="TL-2026-000032",
        record=stage_record("kinematic"),
        device=DEVICE,
        approval=APPROVAL,
        operator="max",
        operator_person=OPERATOR,
        laboratory=LAB,
        software_version="0.1.0",
        issued_on=dt.date(2026, 11, 22),
        begin_on=dt.date(2026, 11, 20),
        standards=STANDARDS[:1],
        measured_points=_placed_points(-2.0, -2.0),
        specification=spec,
    )
    statements = {s.name: s for s in content.statements if isinstance(s, dcc.Statement)}
    zero = statements[
        "statement of conformity: parameter zero_offset.meas_x_deg (deviation from 0 deg)"
    ]
    assert zero.conformity == "pass" and any(
        v.label == "worst_error" and v.expanded_u for v in zero.values
    )
    missing = statements["statement of conformity: parameter no_such_parameter"]
    assert (
        missing.conformity is None
        and "not a parameter of the record's model" in missing.declaration
    )
