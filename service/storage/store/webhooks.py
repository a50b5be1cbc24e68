"""The LIMS event feed and the webhook outbox: endpoints, their deliveries and every attempt."""

from __future__ import annotations

import base64
import datetime as dt
import secrets
from collections.abc import Sequence
from dataclasses import dataclass
from urllib.parse import urlsplit

import sqlalchemy as sa

from service.errors import InputError
from service.storage.errors import UnknownEntity
from service.storage.feed import EVENT_TYPES
from service.storage.models import (
    FeedEvent,
    WebhookAttempt,
    WebhookDelivery,
    WebhookEndpoint,
    utc_now,
)
from service.storage.store.checks import require_text
from service.storage.store.database import Database
from service.storage.store.lookups import row_in

CREDENTIALS_REFUSED = (
    "credentials (user:password@) in a webhook URL would be stored and shown to every admin;"
    " give the URL without them (deliveries are signed with the endpoint's secret, which the"
    " receiver checks)"
)


def webhook_url(url: object) -> str:
    """An http(s) URL with a host and no credentials; anything else is refused before it is
    stored."""
    text = require_text("url", url, 2000)
    try:
        parts = urlsplit(text)
        host = parts.hostname
    except ValueError as exc:
        raise InputError(f"url: not a URL ({exc})") from None
    if parts.scheme not in ("http", "https") or not host:
        raise InputError(
            f"url {shown_url(text)[:100]!r}: a webhook URL must be http:// or https:// with a host"
        )
    if parts.username is not None or parts.password is not None:
        raise InputError(f"url: {CREDENTIALS_REFUSED}")
    return text


def shown_url(url: str) -> str:
    """A stored URL as it may be shown: credentials stored before they were refused are left out."""
    try:
        parts = urlsplit(url)
        if parts.username is None and parts.password is None:
            return url
        netloc = parts.netloc.rsplit("@", 1)[-1]
        return parts._replace(netloc=netloc).geturl()
    except ValueError:
        return url


@dataclass(frozen=True)
class DueDelivery:
    delivery_id: int
    endpoint_id: int
    url: str
    secret: str
    attempts: int
    event: FeedEvent


class FeedRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def events(
        self, *, after_id: int = 0, limit: int = 100, types: Sequence[str] | None = None
    ) -> list[FeedEvent]:
        with self._db.session() as session:
            stmt = (
                sa.select(FeedEvent)
                .where(FeedEvent.id > after_id)
                .order_by(FeedEvent.id)
                .limit(limit)
            )
            if types:
                stmt = stmt.where(FeedEvent.type.in_(list(types)))
            return list(session.scalars(stmt))


class WebhooksRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def add_webhook(
        self, url: object, events: object, *, actor: str
    ) -> tuple[WebhookEndpoint, str]:
        """A webhook endpoint and its signing secret (returned here once; needed in clear to
        sign)."""
        url = webhook_url(url)
        if (
            not isinstance(events, list)
            or not events
            or not all(isinstance(event, str) for event in events)
        ):
            raise InputError(
                f"events must be a non-empty list of event types ({', '.join(EVENT_TYPES)}) or "
                "['*']"
            )
        unknown = [event for event in events if event != "*" and event not in EVENT_TYPES]
        if unknown:
            raise InputError(
                f"events: {', '.join(unknown)} unknown; event types are {', '.join(EVENT_TYPES)} "
                "(or '*')"
            )
        secret = "whsec_" + base64.b64encode(secrets.token_bytes(24)).decode()
        with self._db.transaction() as session:
            row = WebhookEndpoint(
                url=url,
                events=sorted(set(events)),
                secret=secret,
                created_at=utc_now(),
                created_by=require_text("actor", actor),
            )
            session.add(row)
            session.flush()
            self._db.audit(
                session,
                actor,
                "webhook.create",
                "webhook_endpoint",
                row.id,
                {"url": url, "events": row.events},
            )
            return row, secret

    def all(self) -> list[WebhookEndpoint]:
        with self._db.session() as session:
            return list(session.scalars(sa.select(WebhookEndpoint).order_by(WebhookEndpoint.id)))

    def page(self, *, after_id: int | None = None, limit: int = 50) -> list[WebhookEndpoint]:
        """Endpoints in id order from after `after_id` (the cursor), at most `limit`."""
        with self._db.session() as session:
            stmt = sa.select(WebhookEndpoint).order_by(WebhookEndpoint.id).limit(limit)
            if after_id is not None:
                stmt = stmt.where(WebhookEndpoint.id > after_id)
            return list(session.scalars(stmt))

    def get(self, endpoint_id: int) -> WebhookEndpoint:
        with self._db.session() as session:
            return row_in(session, WebhookEndpoint, endpoint_id, "webhook")

    def deliveries(
        self, endpoint_id: int, *, before_id: int | None = None, limit: int = 200
    ) -> list[tuple[WebhookDelivery, FeedEvent, list[WebhookAttempt]]]:
        """An endpoint's deliveries newest first, from before `before_id` (the cursor), with their
        attempts."""
        with self._db.session() as session:
            stmt = (
                sa.select(WebhookDelivery, FeedEvent)
                .join(FeedEvent, FeedEvent.id == WebhookDelivery.event_id)
                .where(WebhookDelivery.endpoint_id == endpoint_id)
                .order_by(WebhookDelivery.id.desc())
                .limit(limit)
            )
            if before_id is not None:
                stmt = stmt.where(WebhookDelivery.id < before_id)
            rows = session.execute(stmt).all()
            ids = [delivery.id for delivery, _ in rows]
            attempts = (
                list(
                    session.scalars(
                        sa.select(WebhookAttempt)
                        .where(WebhookAttempt.delivery_id.in_(ids))
                        .order_by(WebhookAttempt.id)
                    )
                )
                if ids
                else []
            )
        return [
            (
                delivery,
                event,
                [attempt for attempt in attempts if attempt.delivery_id == delivery.id],
            )
            for delivery, event in rows
        ]

    def due_deliveries(self, *, now: dt.datetime, limit: int = 50) -> list[DueDelivery]:
        with self._db.session() as session:
            rows = session.execute(
                sa.select(WebhookDelivery, WebhookEndpoint, FeedEvent)
                .join(WebhookEndpoint, WebhookEndpoint.id == WebhookDelivery.endpoint_id)
                .join(FeedEvent, FeedEvent.id == WebhookDelivery.event_id)
                .where(
                    WebhookDelivery.state == "pending",
                    WebhookDelivery.next_attempt_at <= now,
                    WebhookEndpoint.disabled_at.is_(None),
                )
                .order_by(WebhookDelivery.event_id, WebhookDelivery.id)
                .limit(limit)
            ).all()
        return [
            DueDelivery(
                delivery.id, endpoint.id, endpoint.url, endpoint.secret, delivery.attempts, event
            )
            for delivery, endpoint, event in rows
        ]

    def next_delivery_due(self) -> dt.datetime | None:
        with self._db.session() as session:
            return session.scalar(
                sa.select(sa.func.min(WebhookDelivery.next_attempt_at)).where(
                    WebhookDelivery.state == "pending"
                )
            )

    def record_attempt(
        self,
        delivery_id: int,
        *,
        ok: bool,
        status_code: int | None,
        error: str | None,
        duration_s: float,
        retry_at: dt.datetime | None,
    ) -> WebhookDelivery:
        """Log one attempt; delivered when ok, else pending until `retry_at` (None: given up,
        failed)."""
        now = utc_now()
        with self._db.transaction() as session:
            response = session.get(WebhookDelivery, delivery_id)
            if response is None:
                raise UnknownEntity(f"delivery {delivery_id} does not exist")
            session.add(
                WebhookAttempt(
                    delivery_id=delivery_id,
                    at=now,
                    status_code=status_code,
                    error=(error or None) and error[:2000],
                    duration_s=float(duration_s),
                )
            )
            response.attempts += 1
            response.last_status_code, response.last_error = (
                status_code,
                (error or None) and error[:2000],
            )
            if ok:
                response.state, response.delivered_at, response.next_attempt_at = (
                    "delivered",
                    now,
                    None,
                )
            elif retry_at is None:
                response.state, response.next_attempt_at = "failed", None
            else:
                response.next_attempt_at = retry_at
            return response
