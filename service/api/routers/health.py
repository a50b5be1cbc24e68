from __future__ import annotations

import asyncio
import time
from functools import cache

import sqlalchemy as sa
from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from service import __version__
from service.storage.engine import redacted
from service.storage.migrate import current_revision, head_revision

router = APIRouter(tags=["health"])
_head = cache(head_revision)  # the migration scripts do not change while the daemon runs

REVISION_TTL_S = 1.0  # how old the schema revision /health and /ready report may be


class SchemaRevision:
    """The database's schema revision, asked at most once per `ttl_s` however many requests come.

    Requests never wait for the database once a revision is known: an answer older than `ttl_s`
    is served while one refresh runs in the worker thread pool (a request waiting on it would
    also wait behind every request the event loop has queued meanwhile). Only the first request
    waits for a query. A refresh that fails is not kept: the next request asks the database
    itself, and the failure reaches its caller.
    """

    def __init__(self, ttl_s: float = REVISION_TTL_S) -> None:
        self.ttl_s = ttl_s
        self.queries = 0
        self._value: str | None = None
        self._at: float | None = None
        self._lock = asyncio.Lock()
        self._refresh: asyncio.Task | None = None

    async def _query(self, engine: sa.Engine) -> None:
        self.queries += 1
        try:
            value = await run_in_threadpool(current_revision, engine)
        except BaseException:
            self._at = None
            raise
        self._value, self._at = value, time.monotonic()

    async def get(self, engine: sa.Engine) -> str | None:
        if self._at is None:
            async with self._lock:
                if self._at is None:
                    await self._query(engine)
            return self._value
        if time.monotonic() - self._at >= self.ttl_s and (self._refresh is None or self._refresh.done()):
            self._refresh = asyncio.create_task(self._query(engine))
            self._refresh.add_done_callback(lambda t: t.cancelled() or t.exception())  # failure: see _query
        return self._value

    async def refreshed(self) -> None:
        """Wait for a refresh under way, if any (its failure is not raised here)."""
        if self._refresh is not None:
            await asyncio.gather(self._refresh, return_exceptions=True)


def _revision(request: Request) -> SchemaRevision:
    rev = getattr(request.app.state, "schema_revision", None)
    if rev is None:
        rev = request.app.state.schema_revision = SchemaRevision()
    return rev


@router.get("/health")
async def health(request: Request) -> dict:
    """Liveness plus what the service runs on: version, database and schema revision (as read at most
    one second ago), benches. No token needed."""
    engine = request.app.state.engine
    rev = await _revision(request).get(engine)
    benches = list(request.app.state.benches)
    return {"status": "ok" if rev == _head() else "degraded", "version": __version__,
            "database": redacted(engine.url), "schema_revision": rev,
            "bench": benches[0] if len(benches) == 1 else ", ".join(benches), "benches": benches}


@router.get("/ready")
async def ready(request: Request) -> JSONResponse:
    """Ready for work: the schema at head and every instrument of every bench connected (503 with the
    reasons otherwise). No token needed, like /health."""
    reasons = []
    rev = await _revision(request).get(request.app.state.engine)
    if rev != _head():
        reasons.append(f"database schema at {rev}, not {_head()}")
    for bench in request.app.state.benches.values():
        for st in bench.devices.status():
            if st.state != "connected":
                reasons.append(f"{bench.name}: {st.role} on {st.port} is {st.state}")
    body = {"ready": not reasons, "reasons": reasons}
    return JSONResponse(body, status_code=200 if not reasons else 503)
