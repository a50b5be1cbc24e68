"""The LIMS routes over HTTP on a real database (SQLite and PostgreSQL): scopes, segregation of
duties, certificates issued once and checked, idempotent orders, the feed, and signed webhook
deliveries to a receiver on 127.0.0.1 that verifies every signature with the standardwebhooks
library."""

from __future__ import annotations

import http.server
import json
import threading
import time
from contextlib import asynccontextmanager

import pytest
import sqlalchemy as sa
from fastapi import FastAPI
from fastapi.testclient import TestClient
from standardwebhooks import Webhook

from service.api import problems
from service.api.routers import lims as lims_router
from service.config import Settings
from service.lims import dcc
from service.lims.certificates import verify_certificate
from service.lims.runtime import LimsRuntime
from service.storage.store import Store
from service.storage.tokens import Person
from tests.lims.certificates import stage_record
from tests.storage.storage_helpers import count

STANDARD = {
    "name": "reference inclinometer",
    "serial": "REF-77",
    "certificate_number": "DAkkS-2026-0412",
    "certificate_sha256": "ab" * 32,
    "calibrated_on": "2026-01-10",
    "due_on": "2099-01-10",
    "uncertainty": "0.001 deg (k = 2)",
    "calibrated_by": {
        "name": "Angle Calibration Laboratory AG",
        "accreditation": "D-K-12345-01-00",
        "city": "Hamburg",
        "country_code": "DE",
    },
}
# The people behind the tokens the tests sign with: a record is approved by a person with a
# function.
PEOPLE = {
    "alice": Person("Dr. Alice Example", "Head of Laboratory"),
    "bob": Person("Bob Example", "Deputy Head of Laboratory"),
}
ORDER = {
    "lims_order_id": "LIMS-118",
    "item_serial": "CUST-55",
    "procedure": "stage-grid",
    "method": "homography",
    "due_on": "2026-12-01",
    "customer": {"name": "Survey Ltd", "city": "Berlin", "country_code": "DE"},
}


def make_app(store: Store, tmp_path) -> FastAPI:  # type: ignore[no-untyped-def]
    settings = Settings(
        data_dir=tmp_path,
        lab_name="Inclination Lab GmbH",
        lab_city="Braunschweig",
        lab_country_code="DE",
        webhook_retry_base_s=0.05,
        webhook_retry_max_s=0.2,
        webhook_max_attempts=1000,
    )

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        runtime = LimsRuntime(store, settings)
        app.state.webhooks = runtime.dispatcher
        await runtime.start()
        try:
            yield
        finally:
            await runtime.stop()

    app = FastAPI(lifespan=lifespan)
    problems.install(app)
    app.include_router(lims_router.router)
    app.state.settings, app.state.store = settings, store
    return app


@pytest.fixture
def lab(engine, tmp_path):  # type: ignore[no-untyped-def]
    store = Store(engine)
    tokens = {
        name: store.tokens.create_token(name, scopes, actor="setup", person=PEOPLE.get(name))[1]
        for name, scopes in (
            ("alice", "admin"),
            ("bob", "admin"),
            ("olga", "operate"),
            ("rita", "read"),
        )
    }
    with TestClient(make_app(store, tmp_path)) as client:
        yield store, client, {k: {"Authorization": f"Bearer {v}"} for k, v in tokens.items()}


def measured_record(store: Store, *, started_by: str, order_id: int | None = None, version_of=None):  # type: ignore[no-untyped-def]
    """A record as a job leaves it: real fitted model and validation table, job started by
    `started_by`."""
    device = store.devices.find_device("SCA126T", "SN-4711") or store.devices.add_device(
        "SCA126T", "SN-4711", "measurement_sensor", actor="daemon"
    )
    job = store.jobs.create_job(
        device.id,
        "stage",
        "homography",
        actor=started_by,
        order_id=order_id,
        parameters={"request": {"reference_standards": [1]}},
    )
    store.jobs.start_job(job.id, actor="daemon")
    r = stage_record("homography")
    record = store.records.add_record(
        device.id,
        "stage",
        "homography",
        r["model"],
        operator=started_by,
        job_id=job.id,
        validation=r["validation"],
        temp_c=20.4,
        raw_data={"conditions": {"firmware": {"measurement_sensor": "2.3.1"}}},
    )
    store.jobs.succeed_job(job.id, actor="daemon")
    return record


def test_standards_need_admin_and_show_their_status(lab) -> None:  # type: ignore[no-untyped-def]
    store, client, h = lab
    r = client.post("/standards", json=STANDARD, headers=h["olga"])
    assert r.status_code == 403 and r.headers["content-type"] == "application/problem+json"
    assert client.post("/standards", json=STANDARD).status_code == 401
    r = client.post("/standards", json=STANDARD, headers=h["alice"])
    assert r.status_code == 201 and r.headers["location"] == f"/standards/{r.json()['id']}"
    old = client.post(
        "/standards",
        json={
            **STANDARD,
            "certificate_number": "OLD-1",
            "calibrated_on": "2020-01-01",
            "due_on": "2021-01-01",
        },
        headers=h["alice"],
    ).json()
    assert old["status"] == "past_due"
    r = client.post(
        "/standards", json={**STANDARD, "certificate_sha256": "nothex"}, headers=h["alice"]
    )
    assert r.status_code == 422 and "certificate_sha256" in r.json()["detail"]
    listed = client.get("/standards", headers=h["rita"]).json()["standards"]
    assert [s["status"] for s in listed] == ["valid", "past_due"]
    assert client.get("/standards/99", headers=h["rita"]).status_code == 404


def test_approval_segregation_and_certificate(lab, tmp_path) -> None:  # type: ignore[no-untyped-def]
    store, client, h = lab
    client.post("/standards", json=STANDARD, headers=h["alice"])
    order = client.post(
        "/orders", json=ORDER, headers={**h["olga"], "Idempotency-Key": "o-1"}
    ).json()
    record = measured_record(store, started_by="alice", order_id=order["id"])

    r = client.get(f"/records/{record.id}/certificate", headers=h["rita"])
    assert r.status_code == 409 and "draft" in r.json()["detail"]
    r = client.post(
        f"/records/{record.id}/approve", json={"meaning": "approval"}, headers=h["alice"]
    )
    assert r.status_code == 403 and "segregation of duties" in r.json()["detail"]
    assert count(store.engine, "record_approvals") == 0 and count(store.engine, "certificates") == 0
    # no admin
    assert (
        client.post(f"/records/{record.id}/approve", json={}, headers=h["olga"]).status_code == 403
    )
    r = client.post(
        f"/records/{record.id}/approve",
        json={"meaning": "approval", "note": "residuals fine"},
        headers=h["bob"],
    )
    assert r.status_code == 200 and r.json()["record"]["status"] == "approved"
    assert r.json()["approval"]["record_sha256"] == record.content_sha256

    r = client.get(f"/records/{record.id}/certificate", headers=h["rita"])
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/xml")
    xml = r.content
    assert dcc.certificate_errors(xml) == []
    doc = dcc.dcc_schema().to_dict(xml.decode())
    item = doc["dcc:administrativeData"]["dcc:items"]["dcc:item"][0]
    # the item by the order's serial, then the instrument's own (it reported firmware: it identifies
    # itself)
    assert [i["dcc:value"] for i in item["dcc:identifications"]["dcc:identification"]] == [
        ORDER["item_serial"],
        "SN-4711",
    ]
    signer = [
        p
        for p in doc["dcc:administrativeData"]["dcc:respPersons"]["dcc:respPerson"]
        if p["dcc:mainSigner"]
    ]
    # a person, not a token
    assert signer[0]["dcc:person"]["dcc:name"]["dcc:content"][0]["$"] == "Bob Example"
    assert signer[0]["dcc:role"] == "Deputy Head of Laboratory"
    again = client.get(f"/records/{record.id}/certificate", headers=h["alice"])
    assert again.content == xml and count(store.engine, "certificates") == 1  # never regenerated
    page = client.get(f"/records/{record.id}/certificate.html", headers=h["rita"])
    assert page.status_code == 200 and "SN-4711" in page.text and "Braunschweig" in page.text
    assert client.get(f"/orders/{order['id']}", headers=h["rita"]).json()["state"] == "certified"
    assert verify_certificate(xml, store).ok

    # a second version names the certificate it replaces
    second = measured_record(store, started_by="alice", order_id=order["id"])
    client.post(f"/records/{second.id}/approve", json={"meaning": "approval"}, headers=h["bob"])
    xml2 = client.get(f"/records/{second.id}/certificate", headers=h["rita"]).content
    number1 = dcc.unique_identifier(xml)
    assert (
        f"<dcc:replacedUniqueIdentifier>{number1}</dcc:replacedUniqueIdentifier>".encode() in xml2
    )

    # a tampered stored certificate is detected and not served
    with store.engine.begin() as conn:
        if store.engine.dialect.name == "sqlite":
            conn.exec_driver_sql("DROP TRIGGER trg_certificates_no_update")
        else:
            conn.exec_driver_sql("ALTER TABLE certificates DISABLE TRIGGER USER")
        conn.execute(
            sa.text("UPDATE certificates SET xml = :x WHERE record_id = :r"),
            {"x": xml.replace(b"SN-4711", b"SN-9999"), "r": record.id},
        )
    r = client.get(f"/records/{record.id}/certificate", headers=h["rita"])
    assert r.status_code == 500 and "no longer matches its SHA-256" in r.json()["detail"]
    v = verify_certificate(xml.replace(b"SN-4711", b"SN-9999"), store)
    assert not v.ok and any("altered" in p for p in v.problems)


def test_reject_needs_a_reason_and_is_final(lab) -> None:  # type: ignore[no-untyped-def]
    store, client, h = lab
    record = measured_record(store, started_by="alice")
    assert client.post(f"/records/{record.id}/reject", json={}, headers=h["bob"]).status_code == 422
    r = client.post(
        f"/records/{record.id}/reject",
        json={"reason": "validation above the limit"},
        headers=h["bob"],
    )
    assert r.status_code == 200 and r.json()["record"]["status"] == "rejected"
    assert (
        client.post(f"/records/{record.id}/approve", json={}, headers=h["bob"]).status_code == 409
    )
    assert client.get(f"/records/{record.id}/certificate", headers=h["bob"]).status_code == 409
    assert client.post("/records/999/approve", json={}, headers=h["bob"]).status_code == 404


def test_orders_idempotency_and_webhook_urls(lab) -> None:  # type: ignore[no-untyped-def]
    store, client, h = lab
    first = client.post("/orders", json=ORDER, headers={**h["olga"], "Idempotency-Key": "k1"})
    repeat = client.post("/orders", json=ORDER, headers={**h["olga"], "Idempotency-Key": "k1"})
    assert (first.status_code, repeat.status_code) == (201, 200) and first.json()[
        "id"
    ] == repeat.json()["id"]
    other = client.post(
        "/orders",
        json={**ORDER, "item_serial": "X"},
        headers={**h["olga"], "Idempotency-Key": "k1"},
    )
    assert other.status_code == 422 and "k1" in other.json()["detail"]
    assert client.post("/orders", json=ORDER, headers=h["rita"]).status_code == 403
    assert count(store.engine, "orders") == 1
    for url in ("ftp://x.example/hook", "file:///etc/passwd", "not a url"):
        r = client.post("/webhooks", json={"url": url, "events": ["*"]}, headers=h["alice"])
        assert r.status_code == 422 and "http" in r.json()["detail"]
    assert (
        client.post(
            "/webhooks", json={"url": "http://127.0.0.1:1/", "events": ["*"]}, headers=h["olga"]
        ).status_code
        == 403
    )
    assert count(store.engine, "webhook_endpoints") == 0


def test_feed_pages_with_an_opaque_cursor(lab) -> None:  # type: ignore[no-untyped-def]
    store, client, h = lab
    for i in range(5):
        client.post("/orders", json={**ORDER, "lims_order_id": f"L{i}"}, headers=h["olga"])
    seen, cursor = [], None
    while True:
        page = client.get(
            "/feed",
            params={"limit": 2, **({"cursor": cursor} if cursor else {})},
            headers=h["rita"],
        ).json()
        seen += page["events"]
        if not page["events"]:
            break
        cursor = page["next_cursor"]
    assert [e["data"]["lims_order_id"] for e in seen] == [f"L{i}" for i in range(5)]
    assert len({e["id"] for e in seen}) == 5 and all(e["type"] == "order.created" for e in seen)
    r = client.get("/feed", params={"cursor": "garbage"}, headers=h["rita"])
    assert r.status_code == 422 and "cursor" in r.json()["detail"]


class Receiver:
    """A LIMS's webhook endpoint on 127.0.0.1: verifies each signature, answers 503 while `down`."""

    def __init__(self) -> None:
        self.secret: str | None = None
        self.down = False
        self.ids: list[str] = []
        self.bodies: list[dict] = []  # the events as delivered
        self.bad: list[str] = []
        self.refused = 0
        receiver = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                body = self.rfile.read(int(self.headers["content-length"]))
                if receiver.down:
                    receiver.refused += 1
                    self.send_response(503)
                    self.end_headers()
                    return
                try:
                    event = Webhook(receiver.secret).verify(body, dict(self.headers))
                    assert event["id"] == self.headers["webhook-id"]
                    receiver.ids.append(event["id"])
                    receiver.bodies.append(event)
                except Exception as exc:  # noqa: BLE001 - recorded for the test to fail on
                    receiver.bad.append(repr(exc))
                self.send_response(204)
                self.end_headers()

            def log_message(self, *args) -> None:  # type: ignore[no-untyped-def]
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_port}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def wait_for(predicate, timeout_s: float = 20.0) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.05)


def test_webhooks_are_signed_retried_and_seen_once_each(lab) -> None:  # type: ignore[no-untyped-def]
    store, client, h = lab
    rx = Receiver()
    try:
        r = client.post("/webhooks", json={"url": rx.url, "events": ["*"]}, headers=h["alice"])
        assert r.status_code == 201
        rx.secret = r.json()["secret"]
        hook_id = r.json()["id"]
        rx.down = True
        for i in range(3):
            client.post("/orders", json={**ORDER, "lims_order_id": f"W{i}"}, headers=h["olga"])
        wait_for(lambda: rx.refused >= 3)
        rx.down = False
        record = measured_record(store, started_by="alice")
        client.post(f"/records/{record.id}/approve", json={"meaning": "approval"}, headers=h["bob"])
        feed_ids = [
            e["id"]
            for e in client.get("/feed", params={"limit": 1000}, headers=h["rita"]).json()["events"]
        ]
        wait_for(lambda: set(rx.ids) >= set(feed_ids))
        assert rx.bad == []
        assert sorted(rx.ids) == sorted(feed_ids) and len(rx.ids) == len(set(rx.ids))  # each once

        def log_of() -> list[dict]:
            return client.get(f"/webhooks/{hook_id}/deliveries", headers=h["alice"]).json()[
                "deliveries"
            ]

        # the receiver answers before the daemon writes the attempt down: wait for the log to catch
        # up
        wait_for(lambda: {d["state"] for d in log_of()} == {"delivered"})
        log = log_of()
        retried = [d for d in log if d["attempts"] > 1]
        assert retried and all(d["log"][0]["status_code"] == 503 for d in retried)
    finally:
        rx.close()
    assert json.dumps(log)  # the log is plain JSON
