"""The whole LIMS flow on the daemon with the simulated stage bench and the real drivers: standards,
an order, a job, approval by a second person, the certificate, the feed and signed webhooks."""

from __future__ import annotations

import numpy as np
import pytest
import sqlalchemy as sa

from service.lims import dcc
from tests.helpers.daemon import admin_headers, make_client, wait_job
from tests.helpers.lims import GRID, LAB, ORDER, PEOPLE, STANDARD, Receiver
from tests.helpers.waiting import eventually


def test_order_job_approval_certificate_feed_and_webhooks(tmp_path) -> None:  # type: ignore[no-untyped-def]
    rx = Receiver()
    try:
        with make_client(tmp_path, **LAB) as client:
            store = client.app.state.store
            h = {"admin": admin_headers(tmp_path)}
            for name, scopes in (("alice", "admin"), ("bob", "admin"), ("lims", "operate")):
                person = PEOPLE.get(name)
                secret = store.tokens.create_token(name, scopes, actor="admin", person=person)[1]
                h[name] = {"Authorization": f"Bearer {secret}"}
            hook = client.post(
                "/webhooks", json={"url": rx.url, "events": ["*"]}, headers=h["admin"]
            ).json()
            rx.secret = hook["secret"]
            rx.down = True  # the first deliveries are refused and retried

            good = client.post("/standards", json=STANDARD, headers=h["admin"]).json()
            expired = client.post(
                "/standards",
                json={
                    **STANDARD,
                    "certificate_number": "OLD-2020",
                    "calibrated_on": "2020-01-01",
                    "due_on": "2021-01-01",
                },
                headers=h["admin"],
            ).json()
            order = client.post(
                "/orders",
                json={**ORDER, "item_manufacturer": "Example Sensors", "item_model": "NS-25"},
                headers={**h["lims"], "Idempotency-Key": "lims-118"},
            ).json()
            body = {
                "procedure": "stage-grid",
                "method": "homography",
                "grid": GRID,
                "samples_per_point": 8,
                "validation": {"n_points": 3},
                "order_id": order["id"],
                # windows of 2 bench seconds (0.1 s at 20x): a loaded machine lags the sped-up
                # readings by more than the default 0.5 s window, which then holds no reading and
                # never settles
                "settle": {"tolerance_deg": 0.002, "window_s": 2.0, "timeout_s": 600.0},
            }

            r = client.post(
                "/calibrations",
                json={**body, "reference_standards": [good["id"], expired["id"]]},
                headers=h["alice"],
            )
            assert r.status_code == 422 and "OLD-2020" in r.json()["detail"], r.text
            assert r.json()["field"] == "reference_standards[1]"
            with store.db.session() as s:
                assert s.scalar(sa.text("SELECT count(*) FROM calibration_jobs")) == 0
            r = client.post("/calibrations", json={**body, "order_id": 999}, headers=h["alice"])
            assert r.status_code == 422 and r.json()["field"] == "order_id"

            r = client.post(
                "/calibrations",
                json={**body, "reference_standards": [good["id"]]},
                headers=h["alice"],
            )
            assert r.status_code == 202, r.text
            job = wait_job(client, r.json()["id"], h["alice"])
            assert job["state"] == "succeeded", job
            rid = job["record"]["id"]
            record = client.get(f"/records/{rid}", headers=h["lims"]).json()
            assert record["status"] == "draft"
            assert client.get(f"/records/{rid}/certificate", headers=h["lims"]).status_code == 409
            r = client.post(
                f"/records/{rid}/approve", json={"meaning": "approval"}, headers=h["alice"]
            )
            assert r.status_code == 403  # alice started the job
            rx.down = False
            r = client.post(
                f"/records/{rid}/approve",
                json={"meaning": "approval", "note": "ok"},
                headers=h["bob"],
            )
            assert (
                r.status_code == 200
                and client.get(f"/records/{rid}", headers=h["lims"]).json()["status"] == "approved"
            )

            xml = client.get(f"/records/{rid}/certificate", headers=h["lims"]).content
            assert dcc.certificate_errors(xml) == []
            doc = dcc.dcc_schema().to_dict(xml.decode())
            device = store.devices.get_device(record["device_id"])
            item = doc["dcc:administrativeData"]["dcc:items"]["dcc:item"][0]
            # the item as the order names it: never the bench's port or role, nor the protocol's
            # name as a model
            assert (
                item["dcc:model"] == "NS-25"
                and item["dcc:manufacturer"]["dcc:name"]["dcc:content"][0]["$"] == "Example Sensors"
            )
            ids = [i["dcc:value"] for i in item["dcc:identifications"]["dcc:identification"]]
            assert ids == [ORDER["item_serial"]] and device.serial not in xml.decode()
            model = client.get(f"/records/{rid}/model", headers=h["lims"]).json()
            mr = doc["dcc:measurementResults"]
            results = mr["dcc:measurementResult"][0]["dcc:results"]["dcc:result"]
            reals = {
                q["si:real"]["si:label"]: q["si:real"]
                for q in results[0]["dcc:data"]["dcc:list"][0]["dcc:quantity"]
            }
            # a homography has no bench-only parameters
            assert set(reals) == set(model["parameters"])
            cov = model["covariance"]
            for i, name in enumerate(cov["names"]):
                mu = reals[name]["si:measurementUncertaintyUnivariate"]["si:expandedMU"]
                half_digit = (
                    0.5 * 10 ** (np.floor(np.log10(mu["si:valueExpandedMU"])) - 1) * (1 + 1e-9)
                )
                # GUM-rounded
                assert (
                    abs(reals[name]["si:value"] - model["parameters"][name]["value"]) <= half_digit
                )
                assert (
                    abs(
                        mu["si:valueExpandedMU"]
                        - mu["si:coverageFactor"] * np.sqrt(cov["matrix"][i][i])
                    )
                    <= half_digit + 0.01 * mu["si:valueExpandedMU"]
                )
            table = {
                q["si:realListXMLList"]["si:labelXMLList"][0]: q["si:realListXMLList"]
                for q in results[1]["dcc:data"]["dcc:list"][1]["dcc:quantity"]
            }
            assert len(table["error_x_deg"]["si:valueXMLList"]) == 3
            us = table["measured_x_deg"]["si:measurementUncertaintyUnivariateXMLList"][
                "si:expandedMUXMLList"
            ]["si:valueExpandedMUXMLList"]
            for p, m, U in zip(
                record["validation"]["points"],
                table["measured_x_deg"]["si:valueXMLList"],
                us,
                strict=True,
            ):
                assert abs(p["measured_x_deg"] - m) <= 0.5 * 10 ** (np.floor(np.log10(U)) - 1) * (
                    1 + 1e-9
                )
            # a stage bench's record has the sensors' temperature (0x06 at every point), and so its
            # certificate
            assert record["temp_c"] is not None and 0 < record["temp_c"] < 60, record
            conditions = mr["dcc:influenceConditions"]["dcc:influenceCondition"]
            temperature = next(c for c in conditions if c["@refType"] == ["basic_temperature"])
            mean = temperature["dcc:data"]["dcc:quantity"][0]["si:real"]
            assert (
                abs(mean["si:value"] - record["temp_c"])
                <= 0.5
                * 10
                ** (
                    np.floor(
                        np.log10(
                            mean["si:measurementUncertaintyUnivariate"]["si:expandedMU"][
                                "si:valueExpandedMU"
                            ]
                        )
                    )
                    - 1
                )
                + 1e-9
            )
            eq = mr["dcc:measuringEquipments"]["dcc:measuringEquipment"]
            assert [e["dcc:certificate"]["dcc:value"] for e in eq] == [
                STANDARD["certificate_sha256"]
            ]
            assert (
                client.get(f"/orders/{order['id']}", headers=h["lims"]).json()["state"]
                == "certified"
            )

            feed, cursor = [], None
            while True:
                page = client.get(
                    "/feed",
                    params={"limit": 5, **({"cursor": cursor} if cursor else {})},
                    headers=h["lims"],
                ).json()
                if not page["events"]:
                    break
                feed += page["events"]
                cursor = page["next_cursor"]
            types = [e["type"] for e in feed]
            for t in (
                "order.created",
                "job.state",
                "record.created",
                "record.approved",
                "certificate.issued",
            ):
                assert t in types, t
            job_states = [e["data"]["state"] for e in feed if e["type"] == "job.state"]
            assert job_states[0] == "queued" and job_states[-1] == "succeeded"
            eventually(
                lambda: set(rx.ids) >= {e["id"] for e in feed},
                timeout_s=30,
                every_s=0.05,
                what="every event of the feed delivered",
            )
            log = client.get(f"/webhooks/{hook['id']}/deliveries", headers=h["admin"]).json()[
                "deliveries"
            ]
    finally:
        rx.close()
    assert (
        rx.bad == []
        and sorted(rx.ids) == sorted(e["id"] for e in feed)
        and len(set(rx.ids)) == len(rx.ids)
    )
    assert rx.refused > 0 and any(d["attempts"] > 1 for d in log)


@pytest.mark.parametrize(
    "procedure, method, grid, benches, quantity, unit",
    [
        (
            "scale",
            "poly3",
            # the ADC sensor's null sits near stage x 0.3 deg, and at x -0.2, where the table
            # stands level, it reads seed 003's start state (16 counts): from -0.15 a reading, a
            # mean of 10 conversions scattering by some 8 counts, stays some 230 counts off the
            # converter's end
            {"range_deg": [-0.15, 0.7], "n": 9},
            ["stage"],
            "angle_arcsec",
            r"\arcsecond",
        ),
        (
            "rotation",
            "iodsra",
            {"range_deg": [0, 330], "n": 12},
            ["rotary"],
            "theta_deg",
            r"\degree",
        ),
    ],
)
def test_certificates_of_scale_and_rotation_records(
    tmp_path, procedure, method, grid, benches, quantity, unit
) -> None:  # type: ignore[no-untyped-def]
    with make_client(tmp_path, sim_benches=benches, **LAB) as client:
        store = client.app.state.store
        h = {
            name: {"Authorization": f"Bearer {token}"}
            for name in ("alice", "bob")
            for token in [
                store.tokens.create_token(name, "admin", actor="setup", person=PEOPLE[name])[1]
            ]
        }
        std = client.post("/standards", json=STANDARD, headers=h["alice"]).json()
        r = client.post(
            "/calibrations",
            headers=h["alice"],
            json={
                "procedure": procedure,
                "method": method,
                "grid": grid,
                "samples_per_point": 6,
                "validation": {"n_points": 3},
                "reference_standards": [std["id"]],
            },
        )
        assert r.status_code == 202, r.text
        job = wait_job(client, r.json()["id"], h["alice"])
        assert job["state"] == "succeeded", job["error"]
        rid = job["record"]["id"]
        assert client.post(f"/records/{rid}/approve", json={}, headers=h["bob"]).status_code == 200
        xml = client.get(f"/records/{rid}/certificate", headers=h["bob"]).content
        assert dcc.certificate_errors(xml) == []
        doc = dcc.dcc_schema().to_dict(xml.decode())
        results = doc["dcc:measurementResults"]["dcc:measurementResult"][0]["dcc:results"][
            "dcc:result"
        ]
        table = {
            q["si:realListXMLList"]["si:labelXMLList"][0]: q["si:realListXMLList"]
            for q in results[1]["dcc:data"]["dcc:list"][1]["dcc:quantity"]
        }
        assert table[f"reference_{quantity}"]["si:unitXMLList"] == [unit]
        assert len(table[f"error_{quantity}"]["si:valueXMLList"]) == 3
        record = client.get(f"/records/{rid}", headers=h["bob"]).json()
        assert (
            record["reference_standards"][0]["certificate_sha256"] == STANDARD["certificate_sha256"]
        )
