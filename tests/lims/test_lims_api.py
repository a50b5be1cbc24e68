"""The LIMS routes over HTTP on a real database (SQLite and PostgreSQL): scopes, segregation of
duties, certificates issued once and checked, idempotent orders, the feed, and signed webhook
deliveries to a receiver on 127.0.0.1 that verifies every signature with the standardwebhooks
library."""

from __future__ import annotations

import json
from contextlib import asynccontextmanager

import pytest
import sqlalchemy as sa
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.api import problems
from service.api.routers import lims as lims_router
from service.config import Settings
from service.lims import dcc
from service.lims.certificates import verify_certificate
from service.lims.runtime import LimsRuntime
from service.storage.store import Store
from tests.helpers.lims import ORDER, PEOPLE, STANDARD, Receiver, measured_record
from tests.helpers.storage import count
from tests.helpers.waiting import eventually


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
        eventually(
            lambda: rx.refused >= 3, timeout_s=20, every_s=0.05, what="three deliveries refused"
        )
        rx.down = False
        record = measured_record(store, started_by="alice")
        client.post(f"/records/{record.id}/approve", json={"meaning": "approval"}, headers=h["bob"])
        feed_ids = [
            e["id"]
            for e in client.get("/feed", params={"limit": 1000}, headers=h["rita"]).json()["events"]
        ]
        eventually(
            lambda: set(rx.ids) >= set(feed_ids),
            timeout_s=20,
            every_s=0.05,
            what="every event of the feed delivered",
        )
        assert rx.bad == []
        assert sorted(rx.ids) == sorted(feed_ids) and len(rx.ids) == len(set(rx.ids))  # each once

        def log_of() -> list[dict]:
            return client.get(f"/webhooks/{hook_id}/deliveries", headers=h["alice"]).json()[
                "deliveries"
            ]

        # the receiver answers before the daemon writes the attempt down: wait for the log to catch
        # up
        eventually(
            lambda: {d["state"] for d in log_of()} == {"delivered"},
            timeout_s=20,
            every_s=0.05,
            what="every delivery delivered",
        )
        log = log_of()
        retried = [d for d in log if d["attempts"] > 1]
        assert retried and all(d["log"][0]["status_code"] == 503 for d in retried)
    finally:
        rx.close()
    assert json.dumps(log)  # the log is plain JSON
