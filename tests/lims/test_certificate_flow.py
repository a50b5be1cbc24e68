"""A full flow on the daemon, its simulated stage bench with an ambient sensor: an order with a
specification, a standard naming the laboratory that calibrated it, a job whose conditions the bench
records, approval by a named person; the certificate passes the independent checks (xmllint against
the DCC schema, PTB's dsiunits for every unit, xmlsec1 for the signature) and states what the order
asked, as do the order, the record, the feed and the webhooks. A laboratory that requires conditions
refuses a job without them; a record without a standard is not certified and its budget says why."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import pytest

from service.lims import dcc
from tests.helpers.daemon import make_client, wait_job
from tests.helpers.external_checks import xmllint_errors, xmlsec1_verifies
from tests.helpers.lims import GRID, LAB, ORDER, PEOPLE, STANDARD, Receiver
from tests.helpers.waiting import eventually

NS = {"dcc": dcc.DCC_NS, "si": dcc.SI_NS}
SETTLE = {"tolerance_deg": 0.002, "window_s": 2.0, "timeout_s": 600.0}
SPEC = {"max_permissible_error_deg": 1.0, "decision_rule": "non_binary"}


def _tokens(client) -> dict[str, dict[str, str]]:  # type: ignore[no-untyped-def]
    store = client.app.state.store
    out = {}
    for name, scopes in (("alice", "admin"), ("bob", "admin"), ("lims", "operate")):
        token = store.tokens.create_token(name, scopes, actor="setup", person=PEOPLE.get(name))[1]
        out[name] = {"Authorization": f"Bearer {token}"}
    return out


def test_order_with_specification_to_a_certificate_every_independent_check_accepts(
    tmp_path, lab_signing_files
) -> None:  # type: ignore[no-untyped-def]
    rx = Receiver()
    try:
        with make_client(
            tmp_path, sim_ambient_sensor=True, require_conditions=True, **LAB
        ) as client:
            h = _tokens(client)
            hook = client.post(
                "/webhooks",
                json={"url": rx.url, "events": ["certificate.issued"]},
                headers=h["alice"],
            )
            rx.secret = hook.json()["secret"]
            std = client.post("/standards", json=STANDARD, headers=h["alice"])
            assert (
                std.status_code == 201 and std.json()["calibrated_by"] == STANDARD["calibrated_by"]
            ), std.text
            order = client.post("/orders", json={**ORDER, "specification": SPEC}, headers=h["lims"])
            assert order.status_code == 201, order.text
            assert {k: v for k, v in order.json()["specification"].items() if v is not None} == SPEC
            order_id = order.json()["id"]
            # the bench has an ambient sensor: the job needs no conditions in its request
            r = client.post(
                "/calibrations",
                headers=h["alice"],
                json={
                    "procedure": "stage-grid",
                    "method": "homography",
                    "grid": GRID,
                    "samples_per_point": 8,
                    "validation": {"n_points": 3},
                    "settle": SETTLE,
                    "reference_standards": [std.json()["id"]],
                    "order_id": order_id,
                },
            )
            assert r.status_code == 202, r.text
            job = wait_job(client, r.json()["id"], h["alice"])
            assert job["state"] == "succeeded", job
            rid = job["record"]["id"]
            record = client.get(f"/records/{rid}", headers=h["lims"]).json()
            # the conditions as the bench's thermo-hygrometer read them, against the simulated air
            air = client.app.state.bench.sim.ports["ambient_sensor"].firmware
            temp, humidity = (
                record["conditions"]["ambient_temperature_c"],
                record["conditions"]["relative_humidity_pct"],
            )
            assert temp["source"] == "ambient_sensor" and temp["n_readings"] >= 5, temp
            assert (
                temp["min"] <= temp["value"] <= temp["max"] and temp["standard_uncertainty"] >= 0.1
            )
            assert abs(temp["value"] - air.truth_c()) <= 2 * temp["standard_uncertainty"] + (
                temp["max"] - temp["min"]
            )
            assert abs(humidity["value"] - air.truth_pct()) <= 2 * humidity[
                "standard_uncertainty"
            ] + (humidity["max"] - humidity["min"])
            assert record["budget"]["traceable"] is True and "warning" not in record["budget"]
            # the fit's part of a corrected tilt rests on the measurement fit's one σ: that fit's
            # degrees of freedom
            meas_dof = client.get(f"/records/{rid}/model", headers=h["lims"]).json()["state"][
                "meas_dof"
            ]
            tilt_x = next(r for r in record["budget"]["results"] if r["quantity"] == "tilt_x_deg")
            fit = next(c for c in tilt_x["contributions"] if c["source"] == "fit")
            assert fit["dof"] == pytest.approx(meas_dof, rel=1e-6), (fit, meas_dof)
            conformity = record["conformity"]
            assert (
                conformity["decision_rule"] == "non_binary"
                and conformity["max_permissible_error_deg"] == 1.0
            )
            assert conformity["x"] in ("pass", "conditionalPass", "conditionalFail", "fail")
            assert (
                client.get(f"/orders/{order_id}", headers=h["lims"]).json()["conformity"]
                == conformity
            )

            assert (
                client.post(
                    f"/records/{rid}/approve",
                    json={"meaning": "approval", "note": "ok"},
                    headers=h["bob"],
                ).status_code
                == 200
            )
            xml = client.get(f"/records/{rid}/certificate", headers=h["lims"]).content
            # the independent checks: xmllint (schema), dsiunits (in the reviewer, on every
            # certificate the tests issue: tests/lims/conftest.py), xmlsec1 (signature)
            assert xmllint_errors(xml) == []
            assert xmlsec1_verifies(xml, lab_signing_files[1])
            flipped = bytearray(xml)
            at = xml.index(b"<si:value>", xml.index(b"measurementResults")) + len(b"<si:value>")
            flipped[at] = ord("7") if flipped[at] != ord("7") else ord("8")
            assert not xmlsec1_verifies(bytes(flipped), lab_signing_files[1])
            root = ET.fromstring(xml)
            main = [
                p
                for p in root.findall("dcc:administrativeData/dcc:respPersons/dcc:respPerson", NS)
                if p.findtext("dcc:mainSigner", "", NS) == "true"
            ][0]
            assert main.findtext("dcc:person/dcc:name/dcc:content", "", NS) == PEOPLE["bob"].name
            assert main.findtext("dcc:role", "", NS) == PEOPLE["bob"].function
            operator = [
                p
                for p in root.findall("dcc:administrativeData/dcc:respPersons/dcc:respPerson", NS)
                if p.findtext("dcc:mainSigner", "", NS) == "false"
            ][0]
            assert (
                operator.findtext("dcc:person/dcc:name/dcc:content", "", NS) == PEOPLE["alice"].name
            )
            stated = {
                s.findtext("dcc:name/dcc:content", "", NS): s.findtext("dcc:conformity", "", NS)
                for s in root.findall("dcc:administrativeData/dcc:statements/dcc:statement", NS)
            }
            assert stated["statement of conformity: indication error, x axis"] == conformity["x"]
            assert stated["statement of conformity: indication error, y axis"] == conformity["y"]
            conditions = {
                c.get("refType"): c
                for c in root.findall(
                    "dcc:measurementResults/dcc:influenceConditions/dcc:influenceCondition", NS
                )
            }
            air_xml = conditions["basic_temperature tiltlab_ambientCondition"].find(
                "dcc:data/dcc:quantity/si:real", NS
            )
            assert abs(float(air_xml.findtext("si:value", "", NS)) - temp["value"]) < 0.01
            assert air_xml.find("si:measurementUncertaintyUnivariate/si:standardMU", NS) is not None
            eq = root.find(
                "dcc:measurementResults/dcc:measuringEquipments/dcc:measuringEquipment", NS
            )
            assert "Angle Calibration Laboratory AG" in eq.findtext(
                "dcc:certificate/dcc:referral/dcc:content", "", NS
            )
            assert eq.find("dcc:measuringEquipmentQuantities", NS) is not None
            answer = client.get(f"/records/{rid}/certificate.html", headers=h["lims"])
            page = answer.text
            assert "Statements of conformity" in page and "ambient air temperature" in page
            # a document: nothing in it runs, whatever text was stored (a customer's name, say)
            policy = answer.headers["content-security-policy"]
            assert "default-src 'none'" in policy and "script-src" not in policy, policy
            assert "<script" not in page.lower()
            # the feed and the webhook carry the statements with the issued certificate
            feed = client.get("/feed", params={"limit": 1000}, headers=h["lims"]).json()["events"]
            issued = [e for e in feed if e["type"] == "certificate.issued"]
            assert len(issued) == 1 and issued[0]["data"]["conformity"] == conformity
            eventually(
                lambda: issued[0]["id"] in rx.ids,
                timeout_s=30,
                every_s=0.05,
                what="the certificate's event delivered",
            )
            assert rx.bad == []
            assert [e for e in rx.bodies if e["id"] == issued[0]["id"]][0]["data"][
                "conformity"
            ] == conformity
    finally:
        rx.close()


def test_required_conditions_refuse_a_bare_job_and_no_standard_means_no_certificate(
    tmp_path,
) -> None:  # type: ignore[no-untyped-def]
    with make_client(tmp_path, require_conditions=True, **LAB) as client:
        h = _tokens(client)
        body = {
            "procedure": "stage-grid",
            "method": "homography",
            "grid": GRID,
            "samples_per_point": 8,
            "validation": {"n_points": 3},
            "settle": SETTLE,
        }
        r = client.post("/calibrations", headers=h["alice"], json=body)
        assert r.status_code == 422 and r.json()["field"] == "conditions.ambient_temperature_c", (
            r.text
        )
        assert "no ambient sensor" in r.json()["detail"]
        bad = client.post(
            "/calibrations",
            headers=h["alice"],
            json={
                **body,
                "conditions": {"ambient_temperature_c": {"value": 20.3, "standard_uncertainty": 0}},
            },
        )
        assert bad.status_code == 422 and "standard_uncertainty" in bad.text
        conditions = {
            "ambient_temperature_c": {"value": 20.3, "standard_uncertainty": 0.1},
            "relative_humidity_pct": {"value": 45, "standard_uncertainty": 2},
        }
        r = client.post(
            "/calibrations", headers=h["alice"], json={**body, "conditions": conditions}
        )
        assert r.status_code == 202, r.text
        job = wait_job(client, r.json()["id"], h["alice"])
        assert job["state"] == "succeeded", job
        rid = job["record"]["id"]
        record = client.get(f"/records/{rid}", headers=h["lims"]).json()
        assert record["conditions"]["ambient_temperature_c"] == {
            "value": 20.3,
            "standard_uncertainty": 0.1,
            "source": "request",
        }
        assert record["conditions"]["relative_humidity_pct"]["value"] == 45
        # calibrated without a reference standard: its budget says so, and it is never certified
        assert record["budget"]["traceable"] is False
        assert record["budget"]["warning"] == "no reference standard: not traceable"
        assert (
            client.post(
                f"/records/{rid}/approve", json={"meaning": "approval"}, headers=h["bob"]
            ).status_code
            == 200
        )
        r = client.get(f"/records/{rid}/certificate", headers=h["lims"])
        assert (
            r.status_code == 409 and "no reference standard: not traceable" in r.json()["detail"]
        ), r.text
        assert client.get(f"/records/{rid}/certificate.html", headers=h["lims"]).status_code == 409


@pytest.mark.parametrize("procedure", ["scale"])
def test_a_specification_is_for_stage_grid_orders(tmp_path, procedure: str) -> None:  # type: ignore[no-untyped-def]
    with make_client(tmp_path, **LAB) as client:
        h = _tokens(client)
        r = client.post(
            "/orders",
            headers=h["lims"],
            json={**ORDER, "procedure": procedure, "method": "poly3", "specification": SPEC},
        )
        assert (
            r.status_code == 422
            and r.json()["field"] == "specification"
            and "stage-grid" in r.json()["detail"]
        )
        r = client.post(
            "/orders",
            headers=h["lims"],
            json={**ORDER, "specification": {**SPEC, "guard_band_fraction": 0.5}},
        )
        assert r.status_code == 422 and r.json()["field"] == "specification.guard_band_fraction", (
            r.text
        )
