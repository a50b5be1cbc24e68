"""LIMS storage on SQLite and PostgreSQL: standards, approvals, certificates, orders, the feed, the
outbox."""

from __future__ import annotations

import datetime as dt
import threading

import pytest
import sqlalchemy as sa

from service.errors import InputError
from service.storage.errors import ConflictError, RefusedWrite, UnknownEntity
from service.storage.feed import decode_cursor, encode_cursor
from service.storage.store.approvals import SelfApproval
from service.storage.store.orders import IdempotencyKeyReused
from service.storage.store.standards import StandardNotUsable
from tests.helpers.storage import count

STANDARD = {
    "name": "reference inclinometer",
    "serial": "REF-77",
    "certificate_number": "DAkkS-2026-0412",
    "certificate_sha256": "ab" * 32,
    "calibrated_on": "2026-01-10",
    "due_on": "2027-01-10",
    "uncertainty": "0.001 deg (k = 2)",
}
ORDER = {
    "lims_order_id": "LIMS-118",
    "item_serial": "SN-4711",
    "procedure": "stage-grid",
    "method": "kinematic",
    "due_on": "2026-12-01",
    "customer": {"name": "Survey Ltd", "city": "Berlin", "country_code": "DE"},
}


def record_of_job(lims, *, operator="alice", order_id=None):  # type: ignore[no-untyped-def]
    device = lims.devices.find_device("NS-25", "SN-4711") or lims.devices.add_device(
        "NS-25", "SN-4711", "dut", actor="alice"
    )
    job = lims.jobs.create_job(device.id, "stage", "kinematic", actor=operator, order_id=order_id)
    lims.jobs.start_job(job.id, actor=operator)
    record = lims.records.add_record(
        device.id, "stage", "kinematic", {"parameters": {}}, operator=operator, job_id=job.id
    )
    lims.jobs.succeed_job(job.id, actor=operator)
    return job, record


def test_standards_past_due_are_refused_by_name(lims) -> None:  # type: ignore[no-untyped-def]
    good = lims.standards.add_standard(STANDARD, actor="admin")
    old = lims.standards.add_standard(
        {
            **STANDARD,
            "certificate_number": "DAkkS-2024-0001",
            "calibrated_on": "2024-01-10",
            "due_on": "2025-01-10",
        },
        actor="admin",
    )
    assert [s.id for s in lims.standards.usable_standards([good.id], on=dt.date(2026, 11, 23))] == [
        good.id
    ]
    with pytest.raises(
        StandardNotUsable, match=r"reference_standards\[1\].*DAkkS-2024-0001.*2025-01-10"
    ):
        lims.standards.usable_standards([good.id, old.id], on=dt.date(2026, 11, 23))
    with pytest.raises(StandardNotUsable, match="999 is not a registered"):
        lims.standards.usable_standards([999], on=dt.date(2026, 11, 23))
    for bad, match in (
        ({"certificate_sha256": "XYZ"}, "certificate_sha256"),
        ({"due_on": "2025-01-01"}, "after"),
        ({"calibrated_on": "soon"}, "calibrated_on"),
    ):
        with pytest.raises(InputError, match=match):
            lims.standards.add_standard(
                {**STANDARD, "certificate_number": "X", **bad}, actor="admin"
            )
    with pytest.raises(ConflictError):
        lims.standards.add_standard(STANDARD, actor="admin")
    assert count(lims.engine, "reference_standards") == 2


def test_due_soon_is_announced_once_per_due_date(lims) -> None:  # type: ignore[no-untyped-def]
    s = lims.standards.add_standard(STANDARD, actor="admin")
    assert lims.standards.notify_standards_due(today=dt.date(2026, 11, 23), within_days=30) == []
    assert lims.standards.notify_standards_due(today=dt.date(2026, 12, 20), within_days=30) == [
        s.id
    ]
    assert lims.standards.notify_standards_due(today=dt.date(2026, 12, 21), within_days=30) == []
    (event,) = lims.feed.events(types=["standard.due_soon"])
    assert event.data["standard_id"] == s.id and event.data["days_left"] == 21


def test_segregation_of_duties_and_final_decisions(lims) -> None:  # type: ignore[no-untyped-def]
    job, record = record_of_job(lims, operator="alice")
    before = count(lims.engine, "record_approvals")
    with pytest.raises(SelfApproval, match="segregation of duties"):
        lims.approvals.decide(
            record.id, decision="approve", meaning="approval", note="", actor="alice"
        )
    assert count(lims.engine, "record_approvals") == before
    assert lims.approvals.record_status(record.id) == "draft"
    lims.approvals.decide(
        record.id, decision="approve", meaning="review", note="looked at residuals", actor="bob"
    )
    assert lims.approvals.record_status(record.id) == "draft"  # a review is not the approval
    a = lims.approvals.decide(
        record.id, decision="approve", meaning="approval", note="ok", actor="carol"
    )
    assert lims.approvals.record_status(record.id) == "approved"
    assert a.record_sha256 == record.content_sha256
    with pytest.raises(ConflictError, match="already approved"):
        lims.approvals.decide(
            record.id, decision="reject", meaning="rejection", note="no", actor="bob"
        )
    with pytest.raises(UnknownEntity):
        lims.approvals.decide(9999, decision="approve", meaning="approval", note="", actor="bob")
    assert lims.approvals.verify_approvals() == []
    with pytest.raises(Exception, match="append-only"):
        with lims.engine.begin() as conn:
            conn.execute(sa.text("UPDATE record_approvals SET actor = 'mallory'"))
    _, second = record_of_job(lims, operator="alice")
    with pytest.raises(InputError, match="reason"):
        lims.approvals.decide(second.id, decision="reject", meaning="", note="", actor="bob")
    lims.approvals.decide(
        second.id,
        decision="reject",
        meaning="",
        note="validation error above the limit",
        actor="bob",
    )
    assert lims.approvals.record_status(second.id) == "rejected"
    types = [e.type for e in lims.feed.events()]
    assert (
        types.count("record.approved") == 1
        and "record.reviewed" in types
        and "record.rejected" in types
    )


def test_certificates_are_stored_once_and_never_changed(lims) -> None:  # type: ignore[no-untyped-def]
    _, record = record_of_job(lims)
    a = lims.approvals.decide(
        record.id, decision="approve", meaning="approval", note="", actor="bob"
    )
    cert, created = lims.certificates.store_certificate(
        record.id, number="TL-1", xml=b"<x/>", approval_id=a.id, replaces_id=None, actor="bob"
    )
    again, created2 = lims.certificates.store_certificate(
        record.id, number="TL-2", xml=b"<y/>", approval_id=a.id, replaces_id=None, actor="bob"
    )
    assert created and not created2 and again.id == cert.id and again.xml == b"<x/>"
    with pytest.raises(Exception, match="append-only"):
        with lims.engine.begin() as conn:
            conn.execute(sa.text("UPDATE certificates SET xml = :x"), {"x": b"<z/>"})
    (issued,) = lims.feed.events(types=["certificate.issued"])
    assert issued.data["number"] == "TL-1" and issued.data["sha256"] == cert.sha256


def test_orders_are_idempotent_and_follow_their_jobs(lims) -> None:  # type: ignore[no-untyped-def]
    order, created = lims.orders.create_order(ORDER, actor="lims", idempotency_key="k-1")
    same, created2 = lims.orders.create_order(dict(ORDER), actor="lims", idempotency_key="k-1")
    assert created and not created2 and same.id == order.id
    with pytest.raises(IdempotencyKeyReused, match="k-1"):
        lims.orders.create_order(
            {**ORDER, "item_serial": "OTHER"}, actor="lims", idempotency_key="k-1"
        )
    with pytest.raises(ConflictError, match="LIMS-118"):
        lims.orders.create_order(ORDER, actor="lims", idempotency_key="k-2")
    with pytest.raises(InputError, match="country_code"):
        lims.orders.create_order(
            {
                **ORDER,
                "lims_order_id": "X",
                "customer": {"name": "a", "city": "b", "country_code": "de"},
            },
            actor="lims",
        )
    assert count(lims.engine, "orders") == 1
    assert lims.orders.order_links(order.id)["state"] == "open"
    _, record = record_of_job(lims, order_id=order.id)
    assert lims.orders.order_links(order.id)["state"] == "measured"
    a = lims.approvals.decide(
        record.id, decision="approve", meaning="approval", note="", actor="bob"
    )
    assert lims.orders.order_links(order.id)["state"] == "approved"
    lims.certificates.store_certificate(
        record.id, number="TL-9", xml=b"<x/>", approval_id=a.id, replaces_id=None, actor="bob"
    )
    links = lims.orders.order_links(order.id)
    assert links["state"] == "certified" and links["certificates"][0]["number"] == "TL-9"
    job_events = [e.data for e in lims.feed.events(types=["job.state"])]
    assert [d["state"] for d in job_events] == ["queued", "running", "succeeded"]
    assert all(d["order_id"] == order.id for d in job_events)


def test_feed_cursor_is_opaque_and_checked() -> None:
    assert decode_cursor(encode_cursor(12345)) == 12345 and decode_cursor(None) == 0
    assert "12345" not in encode_cursor(12345)
    for bad in ("12", "f1.!!", "f1." + "LTE"):  # "LTE" is base64 of -1
        with pytest.raises(InputError, match="cursor"):
            decode_cursor(bad)


def test_polling_while_writers_write_misses_and_repeats_nothing(lims) -> None:  # type: ignore[no-untyped-def]
    """Writers in threads append events while a reader pages through the feed with its cursor."""
    writers, per_writer = 4, 15
    done = threading.Event()
    errors: list[BaseException] = []

    def write(w: int) -> None:
        try:
            for i in range(per_writer):
                lims.orders.create_order(
                    {**ORDER, "lims_order_id": f"W{w}-{i}"}, actor=f"writer{w}"
                )
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    seen: list[int] = []

    def poll() -> None:
        cursor = None
        while True:
            finished = done.is_set()
            page = lims.feed.events(after_id=decode_cursor(cursor), limit=7)
            seen.extend(e.id for e in page)
            if page:
                cursor = encode_cursor(page[-1].id)
            elif finished:
                return

    reader = threading.Thread(target=poll)
    threads = [threading.Thread(target=write, args=(w,)) for w in range(writers)]
    reader.start()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    done.set()
    reader.join(timeout=60)
    assert not errors
    all_ids = [e.id for e in lims.feed.events(limit=10_000)]
    assert len(all_ids) == writers * per_writer
    assert seen == all_ids  # every event once, in order


def test_webhook_endpoints_and_the_outbox(lims) -> None:  # type: ignore[no-untyped-def]
    for url in ("ftp://example.org/x", "file:///etc/passwd", "http://", "javascript:alert(1)"):
        with pytest.raises(InputError, match="http"):
            lims.webhooks.add_webhook(url, ["*"], actor="admin")
    with pytest.raises(InputError, match="unknown"):
        lims.webhooks.add_webhook("http://127.0.0.1:9/hook", ["job.exploded"], actor="admin")
    assert count(lims.engine, "webhook_endpoints") == 0
    all_events, secret = lims.webhooks.add_webhook("http://127.0.0.1:9/all", ["*"], actor="admin")
    orders_only, _ = lims.webhooks.add_webhook(
        "https://lims.example/hook", ["order.created"], actor="admin"
    )
    assert secret.startswith("whsec_")
    lims.orders.create_order(ORDER, actor="lims")
    record_of_job(lims)
    due = lims.webhooks.due_deliveries(now=dt.datetime.now(dt.UTC) + dt.timedelta(seconds=1))
    assert {d.endpoint_id for d in due} == {all_events.id, orders_only.id}
    assert [d.event.type for d in due if d.endpoint_id == orders_only.id] == ["order.created"]
    first = due[0]
    retry = dt.datetime.now(dt.UTC) + dt.timedelta(seconds=60)
    lims.webhooks.record_attempt(
        first.delivery_id, ok=False, status_code=503, error="down", duration_s=0.01, retry_at=retry
    )
    assert first.delivery_id not in {
        d.delivery_id for d in lims.webhooks.due_deliveries(now=dt.datetime.now(dt.UTC))
    }
    lims.webhooks.record_attempt(
        first.delivery_id, ok=True, status_code=204, error=None, duration_s=0.01, retry_at=None
    )
    (log,) = [
        (d, a)
        for d, _, a in lims.webhooks.deliveries(first.endpoint_id)
        if d.id == first.delivery_id
    ]
    assert log[0].state == "delivered" and [x.status_code for x in log[1]] == [503, 204]


def test_tampered_record_cannot_be_signed(lims) -> None:  # type: ignore[no-untyped-def]
    _, record = record_of_job(lims)
    with lims.engine.begin() as conn:
        if lims.engine.dialect.name == "sqlite":
            conn.exec_driver_sql("DROP TRIGGER trg_calibration_records_no_update")
        else:
            conn.exec_driver_sql("ALTER TABLE calibration_records DISABLE TRIGGER USER")
        conn.execute(
            sa.text("UPDATE calibration_records SET method = 'homography' WHERE id = :i"),
            {"i": record.id},
        )
    with pytest.raises(RefusedWrite, match="tampered"):
        lims.approvals.decide(
            record.id, decision="approve", meaning="approval", note="", actor="bob"
        )


def test_db_verify_covers_approvals_and_certificates(lims) -> None:  # type: ignore[no-untyped-def]
    from service.storage.verify import verify

    _, record = record_of_job(lims)
    a = lims.approvals.decide(
        record.id, decision="approve", meaning="approval", note="", actor="bob"
    )
    lims.certificates.store_certificate(
        record.id, number="TL-1", xml=b"<x/>", approval_id=a.id, replaces_id=None, actor="bob"
    )
    assert verify(lims.engine).ok
    with lims.engine.begin() as conn:
        if lims.engine.dialect.name == "sqlite":
            conn.exec_driver_sql("DROP TRIGGER trg_certificates_no_update")
            conn.exec_driver_sql("DROP TRIGGER trg_record_approvals_no_update")
        else:
            conn.exec_driver_sql("ALTER TABLE certificates DISABLE TRIGGER USER")
            conn.exec_driver_sql("ALTER TABLE record_approvals DISABLE TRIGGER USER")
        conn.execute(sa.text("UPDATE certificates SET xml = :x"), {"x": b"<y/>"})
        conn.execute(sa.text("UPDATE record_approvals SET note = 'changed'"))
    kinds = {(p.table, p.kind) for p in verify(lims.engine).problems}
    assert kinds == {("certificates", "tampered"), ("record_approvals", "tampered")}


def test_back_off_doubles_to_its_cap_and_a_delivery_can_be_given_up(lims) -> None:  # type: ignore[no-untyped-def]
    from service.lims.webhooks import retry_delay_s

    assert [retry_delay_s(n, 5.0, 60.0) for n in (1, 2, 3, 4, 5, 6)] == [
        5.0,
        10.0,
        20.0,
        40.0,
        60.0,
        60.0,
    ]
    hook, _ = lims.webhooks.add_webhook("http://127.0.0.1:9/x", ["order.created"], actor="admin")
    lims.orders.create_order(ORDER, actor="lims")
    (due,) = lims.webhooks.due_deliveries(now=dt.datetime.now(dt.UTC) + dt.timedelta(seconds=1))
    lims.webhooks.record_attempt(
        due.delivery_id, ok=False, status_code=None, error="refused", duration_s=0.0, retry_at=None
    )
    assert lims.webhooks.due_deliveries(now=dt.datetime.now(dt.UTC) + dt.timedelta(days=1)) == []
    ((delivery, _, attempts),) = lims.webhooks.deliveries(hook.id)
    assert delivery.state == "failed" and attempts[0].error == "refused"
