"""Webhook delivery per the Standard Webhooks specification, from the durable outbox.

Each pending delivery is POSTed with `webhook-id` (the event's id: a receiver deduplicates on it),
`webhook-timestamp` and `webhook-signature` (HMAC-SHA256 by the `standardwebhooks` library); the
body is the feed's event. A 2xx answer delivers it; anything else is retried after base·2^(n-1)
seconds (capped) until the attempts run out. The outbox is in the database, so deliveries pending
when the daemon stops are sent after it starts again.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import logging
import time

import httpx
from standardwebhooks import Webhook

from service.config import Settings
from service.storage.feed import event_json
from service.storage.outage import reason_of, unreachable
from service.storage.store.webhooks import DueDelivery, WebhooksRepo

log = logging.getLogger("tiltlab.webhooks")


def body_of(delivery: DueDelivery) -> str:
    return json.dumps(event_json(delivery.event), separators=(",", ":"), ensure_ascii=False)


def signed_headers(delivery: DueDelivery, body: str, now: dt.datetime) -> dict[str, str]:
    msg_id = event_json(delivery.event)["id"]
    return {
        "content-type": "application/json",
        "webhook-id": msg_id,
        "webhook-timestamp": str(int(now.timestamp())),
        "webhook-signature": Webhook(delivery.secret).sign(msg_id, now, body),
        "user-agent": "tiltlab-webhooks",
    }


def retry_delay_s(attempts_done: int, base_s: float, max_s: float) -> float:
    """Exponential back-off: base, 2·base, 4·base, ... capped at max_s."""
    return min(max_s, base_s * 2.0 ** max(attempts_done - 1, 0))


class Dispatcher:
    """Runs in the daemon: sends due deliveries, sleeps until the next one is due (or it is
    woken)."""

    def __init__(self, webhooks: WebhooksRepo, settings: Settings) -> None:
        self.webhooks, self.settings = webhooks, settings
        self.wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._task = asyncio.create_task(self.run(), name="webhook-dispatcher")

    def nudge(self) -> None:
        """Wake the dispatcher to send what is due now. Safe from any thread: routes that store a
        webhook run off the event loop, and an asyncio.Event set from another thread corrupts its
        waiters."""
        loop = self._loop
        if loop is None:  # not started: nothing waits on the event
            self.wake.set()
            return
        try:
            on_loop = asyncio.get_running_loop() is loop
        except RuntimeError:
            on_loop = False
        if on_loop:
            self.wake.set()
        elif not loop.is_closed():
            loop.call_soon_threadsafe(self.wake.set)

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass

    async def run(self) -> None:
        async with httpx.AsyncClient(
            timeout=self.settings.webhook_timeout_s, follow_redirects=False
        ) as client:
            while True:
                try:
                    sent = await self.send_due(client)
                except asyncio.CancelledError:
                    raise
                except Exception as exc:  # noqa: BLE001 - a database hiccup must not end deliveries; retried below
                    if unreachable(exc):
                        log.warning(
                            "webhook dispatcher: the database is away (%s); retrying",
                            reason_of(exc),
                        )
                    else:
                        log.exception("webhook dispatcher: a round failed; retrying")
                    sent = 0
                if sent:
                    continue
                await self._sleep_until_due()

    async def _sleep_until_due(self) -> None:
        try:
            nxt = await asyncio.to_thread(self.webhooks.next_delivery_due)
        except Exception:  # noqa: BLE001 - the database away: asked again in a second, the dispatcher goes on
            nxt = None
        wait_s = 1.0
        if nxt is not None:
            wait_s = min(1.0, max(0.0, (nxt - dt.datetime.now(dt.UTC)).total_seconds()))
        self.wake.clear()
        try:
            await asyncio.wait_for(self.wake.wait(), timeout=max(wait_s, 0.02))
        except TimeoutError:
            pass

    async def send_due(self, client: httpx.AsyncClient) -> int:
        due = await asyncio.to_thread(self.webhooks.due_deliveries, now=dt.datetime.now(dt.UTC))
        for delivery in due:
            await self.deliver(client, delivery)
        return len(due)

    async def deliver(self, client: httpx.AsyncClient, d: DueDelivery) -> None:
        body = body_of(d)
        now = dt.datetime.now(dt.UTC)
        started = time.monotonic()
        status: int | None = None
        error: str | None = None
        try:
            response = await client.post(
                d.url, content=body.encode("utf-8"), headers=signed_headers(d, body, now)
            )
            status = response.status_code
            if not 200 <= status < 300:
                error = f"HTTP {status}: {response.text[:200]}"
        except httpx.HTTPError as exc:
            error = f"{type(exc).__name__}: {exc}"
        duration = time.monotonic() - started
        ok = error is None
        retry_at = None
        if not ok and d.attempts + 1 < self.settings.webhook_max_attempts:
            delay = retry_delay_s(
                d.attempts + 1,
                self.settings.webhook_retry_base_s,
                self.settings.webhook_retry_max_s,
            )
            retry_at = dt.datetime.now(dt.UTC) + dt.timedelta(seconds=delay)
        await asyncio.to_thread(
            self.webhooks.record_attempt,
            d.delivery_id,
            ok=ok,
            status_code=status,
            error=error,
            duration_s=duration,
            retry_at=retry_at,
        )
        if not ok:
            log.info("webhook %s to %s: %s (attempt %d)", d.event.id, d.url, error, d.attempts + 1)
