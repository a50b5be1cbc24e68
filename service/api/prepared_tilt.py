"""`GET /tilt` answered in front of the routing table for the callers the daemon already knows.

`/tilt` is the route a client polls, hundreds of times a second. Its answer needs three things the
daemon holds in memory (the bench, the job manager's active record, the caller's token in the token
cache), yet the full path through the routers resolves the same dependencies, matches the path
against every route and passes four middlewares for each request. This layer answers the plain case
directly, with the route's own body (`tilt_answer`) and the same headers and metrics: a GET without
a body, no query or only `bench=<a bench of this node>`, a token the daemon knows and that may read,
a daemon running alone (not in a fleet). Anything else (no token, an unknown or revoked one, a
HEAD, another node's bench, an error while answering) goes on to the full application, which
answers exactly as it always did. A revocation clears the token cache, so it takes effect here at
once.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any
from urllib.parse import parse_qsl

from starlette.types import ASGIApp, Receive, Scope, Send

from service.api.auth import TokenChecks
from service.api.routers.tilt import tilt_answer
from service.bench.runtime import BenchRuntime

PATH = "/tilt"
MAX_BENCH_NAME = 100  # the route's own limit on `bench`
_BODY_HEADERS = (b"content-length", b"transfer-encoding")


class PreparedTilt:
    """Answers `GET /tilt` for a known reader without the routing table; passes everything else
    on."""

    def __init__(self, app: ASGIApp, state_of: Any) -> None:
        self.app = app
        self._state_of = state_of  # the FastAPI application, whose state the lifespan fills

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] != PATH or scope["method"] != "GET":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        body = self._answer(scope)
        if body is None:
            await self.app(scope, receive, send)
            return
        await send(
            {
                "type": "http.response.start",
                "status": 200,
                "headers": [
                    (b"content-length", str(len(body)).encode()),
                    (b"content-type", b"application/json"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})
        metrics = getattr(self._state_of.state, "metrics", None)
        if metrics is not None:
            metrics.observe(PATH, "GET", 200, time.perf_counter() - start)

    def _answer(self, scope: Scope) -> bytes | None:
        """The answer's body when this is the plain case, else None (the full application
        answers)."""
        state = self._state_of.state
        benches = getattr(state, "benches", None)
        jobs = getattr(state, "jobs", None)
        settings = getattr(state, "settings", None)
        if (
            benches is None
            or jobs is None
            or settings is None
            or getattr(state, "fleet", None) is not None
        ):
            return None
        authorization, has_body = _authorization_of(scope)
        if has_body:
            return None
        if settings.auth != "none" and not _may_read(
            getattr(state, "token_checks", None), authorization
        ):
            return None
        bench = _bench_asked(scope, benches)
        if bench is None:
            return None
        try:
            return tilt_answer(bench, jobs)
        except Exception:
            return None  # the full application answers it, with its own error handling


def _authorization_of(scope: Scope) -> tuple[bytes, bool]:
    """The request's first Authorization header (as the route reads; empty when it has none), and
    whether a header says it has a body (then it is not the plain case)."""
    authorization = None
    for name, value in scope["headers"]:
        if name == b"authorization":
            authorization = value if authorization is None else authorization
        elif name in _BODY_HEADERS:
            return authorization or b"", True
    return authorization or b"", False


def _bench_asked(scope: Scope, benches: Mapping[str, BenchRuntime]) -> BenchRuntime | None:
    """The bench the query names (`bench=<name>` and nothing else), or the only bench when it names
    none; None when neither fits."""
    query = scope.get("query_string", b"")
    if query:
        pairs = parse_qsl(query.decode("latin-1"), keep_blank_values=True)
        if len(pairs) != 1 or pairs[0][0] != "bench" or len(pairs[0][1]) > MAX_BENCH_NAME:
            return None
        return benches.get(pairs[0][1])
    return next(iter(benches.values())) if len(benches) == 1 else None


def _may_read(checks: TokenChecks | None, authorization: bytes) -> bool:
    scheme, _, value = authorization.decode("latin-1").partition(" ")
    token = value.strip()
    if checks is None or scheme.lower() != "bearer" or not token:
        return False
    principal = checks.known(token)  # re-checked in the background when its answer is old
    return principal is not None and principal.may("read")
