"""The database's schema revision as /health and /ready report it, asked at most once a second."""

from __future__ import annotations

import asyncio
import time

import sqlalchemy as sa
from starlette.concurrency import run_in_threadpool

from service.storage.migrate import current_revision
from service.storage.outage import DatabaseState, unreachable

REVISION_TTL_S = 1.0  # how old the schema revision /health and /ready report may be


class SchemaRevision:
    """The database's schema revision, asked at most once per `ttl_s` however many requests come.

    Requests never wait for the database once a revision is known: an answer older than `ttl_s`
    is served while one refresh runs in the worker thread pool (a request waiting on it would
    also wait behind every request the event loop has queued meanwhile). Only the first request
    waits for a query. A refresh that fails is not kept: the next request asks the database
    itself, and the failure reaches its caller; but a refresh that finds the database away keeps
    the revision known before and tells `database` (so /health answers through an outage and says
    so).
    """

    def __init__(
        self, ttl_s: float = REVISION_TTL_S, database: DatabaseState | None = None
    ) -> None:
        self.ttl_s = ttl_s
        self.database = database
        self.queries = 0
        self._value: str | None = None
        self._at: float | None = None
        self._lock = asyncio.Lock()
        self._refresh: asyncio.Task[None] | None = None

    async def _query(self, engine: sa.Engine) -> None:
        self.queries += 1
        try:
            value = await run_in_threadpool(current_revision, engine)
        except BaseException as exc:
            if self.database is not None and unreachable(exc):
                self.database.away(exc)
                # the revision known before stands; asked again after ttl_s
                if self._at is not None:
                    self._at = time.monotonic()
                    return
            self._at = None
            raise
        if self.database is not None:
            self.database.back()
        self._value, self._at = value, time.monotonic()

    async def get(self, engine: sa.Engine) -> str | None:
        if self._at is None:
            async with self._lock:
                if self._at is None:
                    await self._query(engine)
            return self._value
        if time.monotonic() - self._at >= self.ttl_s and (
            self._refresh is None or self._refresh.done()
        ):
            self._refresh = asyncio.create_task(self._query(engine))
            # failure: see _query
            self._refresh.add_done_callback(lambda t: t.cancelled() or t.exception())
        return self._value

    async def refreshed(self) -> None:
        """Wait for a refresh under way, if any (its failure is not raised here)."""
        if self._refresh is not None:
            await asyncio.gather(self._refresh, return_exceptions=True)
