"""The LIMS integration against `tiltlab serve` in a subprocess: a LIMS-like client polls the feed
while events are written, a webhook receiver on 127.0.0.1 verifies every signature and sees every
event once, also after being down and across a restart of the daemon with deliveries pending."""

from __future__ import annotations

import threading
import time

import httpx

from service.config import Settings
from service.lims import dcc
from service.storage.migrate import bootstrap
from service.storage.store import Store
from tests.helpers.lims import ORDER, PEOPLE, STANDARD, Receiver, measured_record
from tests.helpers.running_service import running_service
from tests.helpers.waiting import eventually

ENV = {
    "TILTLAB_LAB_NAME": "Inclination Lab GmbH",
    "TILTLAB_LAB_CITY": "Braunschweig",
    "TILTLAB_LAB_COUNTRY_CODE": "DE",
    "TILTLAB_WEBHOOK_RETRY_BASE_S": "0.2",
    "TILTLAB_WEBHOOK_RETRY_MAX_S": "0.5",
    "TILTLAB_WEBHOOK_MAX_ATTEMPTS": "1000",
}


class FeedClient:
    """What a LIMS does: poll /feed with the cursor it was given, in its own thread."""

    def __init__(self, base: str, token: str) -> None:
        self.base, self.headers = base, {"Authorization": f"Bearer {token}"}
        self.cursor: str | None = None
        self.events: list[dict] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)

    def poll_once(self) -> int:
        params = {"limit": 3, **({"cursor": self.cursor} if self.cursor else {})}
        page = (
            httpx.get(f"{self.base}/feed", params=params, headers=self.headers, timeout=10)
            .raise_for_status()
            .json()
        )
        self.events += page["events"]
        self.cursor = page["next_cursor"]
        return len(page["events"])

    def run(self) -> None:
        while not self.stop.is_set():
            if not self.poll_once():
                time.sleep(0.02)

    def drain(self) -> None:
        while self.poll_once():
            pass


def test_feed_and_webhooks_across_a_restart(tmp_path) -> None:  # type: ignore[no-untyped-def]
    data = tmp_path / "data"
    engine = bootstrap(Settings(data_dir=data))
    store = Store(engine)
    tokens = {
        n: store.tokens.create_token(n, s, actor="setup", person=PEOPLE.get(n))[1]
        for n, s in (("alice", "admin"), ("bob", "admin"), ("olga", "operate"), ("lims", "read"))
    }
    h = {n: {"Authorization": f"Bearer {t}"} for n, t in tokens.items()}
    rx = Receiver()
    try:
        with running_service(data, **ENV) as base:
            hook = httpx.post(
                f"{base}/webhooks", json={"url": rx.url, "events": ["*"]}, headers=h["alice"]
            ).json()
            rx.secret = hook["secret"]
            rx.down = True  # the LIMS's receiver is down: deliveries wait in the outbox
            poller = FeedClient(base, tokens["lims"])
            poller.thread.start()
            writers = [
                threading.Thread(
                    target=lambda w=w: [
                        httpx.post(
                            f"{base}/orders",
                            json={**ORDER, "lims_order_id": f"W{w}-{i}"},
                            headers=h["olga"],
                            timeout=10,
                        )
                        for i in range(6)
                    ]
                )
                for w in range(3)
            ]
            for t in writers:
                t.start()
            for t in writers:
                t.join()
            assert (
                httpx.post(f"{base}/standards", json=STANDARD, headers=h["alice"]).status_code
                == 201
            )
            eventually(
                lambda: rx.refused >= 3, timeout_s=20, every_s=0.05, what="three deliveries refused"
            )
            poller.stop.set()
            poller.thread.join()
        # the daemon is stopped with deliveries pending; the receiver comes back; the daemon starts
        # again
        rx.down = False
        with running_service(data, **ENV) as base:
            record = measured_record(store, started_by="olga")
            r = httpx.post(
                f"{base}/records/{record.id}/approve",
                json={"meaning": "approval"},
                headers=h["olga"],
            )
            assert r.status_code == 403  # no admin scope
            assert (
                httpx.get(f"{base}/records/{record.id}/certificate", headers=h["lims"]).status_code
                == 409
            )
            r = httpx.post(
                f"{base}/records/{record.id}/approve",
                json={"meaning": "approval"},
                headers=h["bob"],
            )
            assert r.status_code == 200
            xml = httpx.get(f"{base}/records/{record.id}/certificate", headers=h["lims"]).content
            assert dcc.certificate_errors(xml) == []
            poller.base = base
            poller.drain()
            feed_ids = [e["id"] for e in poller.events]
            eventually(
                lambda: set(rx.ids) >= set(feed_ids),
                timeout_s=30,
                every_s=0.05,
                what="every event of the feed delivered",
            )

            def log_of() -> list[dict]:
                return httpx.get(
                    f"{base}/webhooks/{hook['id']}/deliveries", headers=h["alice"]
                ).json()["deliveries"]

            # the log follows the receiver
            eventually(
                lambda: {d["state"] for d in log_of()} == {"delivered"},
                timeout_s=20,
                every_s=0.05,
                what="every delivery delivered",
            )
            log = log_of()
    finally:
        rx.close()
        engine.dispose()
    types = [e["type"] for e in poller.events]
    assert (
        types.count("order.created") == 18
        and "certificate.issued" in types
        and "record.approved" in types
    )
    assert len(feed_ids) == len(set(feed_ids))  # the poller got each event once ...
    numbers = [int(i.removeprefix("evt_")) for i in feed_ids]
    assert numbers == sorted(numbers)  # ... in order
    assert rx.bad == [] and sorted(rx.ids) == sorted(feed_ids) and len(rx.ids) == len(set(rx.ids))
    assert {d["state"] for d in log} == {"delivered"} and any(d["attempts"] > 1 for d in log)
