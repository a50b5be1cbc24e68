"""Bearer tokens and scopes on every route but /health, /ready, the dashboard and the API's own
pages.

`Authorization: Bearer <token>` on HTTP. On WebSockets (browsers cannot set headers there) the
subprotocol `bearer.<token>` (`Sec-WebSocket-Protocol`, kept out of URLs and so out of logs) or the
`token` query parameter. 401 without a valid token, 403 without the scope the route needs.

The token is checked before anything else looks at a request (`Authentication`, in front of the
routing table): a stranger learns nothing of benches, records or the shape of a body from a 404 or
a 422, only 401. The check never waits on the event loop: a token the daemon knows is answered
from memory (`TokenCache`), any other is asked of the database in the request threads with a
deadline (service/api/offloop.py), and a database that does not answer in time is a 503 naming it.
Unknown tokens from one address are slowed down (`FailedTokens`: 429 with Retry-After).
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import math
import time
from collections.abc import Awaitable, Callable
from typing import Annotated, Any

from fastapi import Depends, Request, WebSocket
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.types import ASGIApp, Receive, Scope, Send

from service.api.offloop import DatabaseCalls, DatabaseSlow, use_calls
from service.api.problems import ProblemError, problem
from service.storage.outage import DatabaseState, unreachable
from service.storage.tokens import SCOPES, Principal

log = logging.getLogger("tiltlab.auth")

EVERYONE = Principal("anonymous (authentication off)", frozenset(SCOPES))
# where the middleware leaves the request's principal in its ASGI scope
PRINCIPAL = "tiltlab.principal"

# The OpenAPI document's security scheme (`bearerAuth`); the header itself is read by the middleware
# so that a missing or malformed one is a 401 problem, not FastAPI's own answer.
BEARER = HTTPBearer(
    scheme_name="bearerAuth",
    auto_error=False,
    description="a token of `tiltlab token create` (or the admin token file); scopes read, "
    "operate, admin",
)

# What needs no token: liveness and readiness, the dashboard's page and files, the API's own pages.
PUBLIC_PATHS = frozenset(
    {
        "/health",
        "/ready",
        "/",
        "/docs",
        "/docs/oauth2-redirect",
        "/redoc",
        "/openapi.json",
        "/favicon.ico",
    }
)
PUBLIC_PREFIXES = ("/web/", "/docs-assets/", "/redoc-assets/")
UNAUTHORIZED = {"WWW-Authenticate": 'Bearer realm="tiltlab"'}
INVALID = {"WWW-Authenticate": 'Bearer realm="tiltlab", error="invalid_token"'}


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def is_public(path: str) -> bool:
    return path in PUBLIC_PATHS or path.startswith(PUBLIC_PREFIXES)


def bearer_of(headers: Any) -> str | None:
    """The token of the first `Authorization: Bearer <token>` header of an ASGI scope's headers."""
    for name, value in headers:
        if name == b"authorization":
            scheme, _, token = value.decode("latin-1").partition(" ")
            token = token.strip()
            return token if scheme.lower() == "bearer" and token else None
    return None


def client_address(scope: Scope) -> str:
    client = scope.get("client")
    return str(client[0]) if client else "unknown"


class TokenCache:
    """What the database last said of each token presented, so a busy reader costs no query per
    request.

    The rules: an answer is fresh for `ttl_s` seconds and used as it is. A valid token whose answer
    is older is still answered from memory while one re-check runs in the background (its next
    request has the database's answer), so a request never waits for the database on behalf of a
    token the daemon knows. A revocation through this daemon clears the cache at once; one made by
    `tiltlab token revoke` elsewhere takes effect within `ttl_s` (plus the one re-check). While the
    database does not answer, a valid token keeps its last answer (asked again every `ttl_s`): the
    daemon goes on serving its benches to the people it knew, and no revocation can be written
    meanwhile anyway. Tokens found invalid are remembered for `ttl_s` too, at most `max_invalid` of
    them (then forgotten all at once); valid ones are as many as the database holds.
    """

    def __init__(self, ttl_s: float = 5.0, max_invalid: int = 10_000) -> None:
        self.ttl_s = ttl_s
        self.max_invalid = max_invalid
        self._valid: dict[str, tuple[float, Principal]] = {}
        self._invalid: dict[str, float] = {}

    def answer(self, token: str) -> tuple[Principal | None, bool] | None:
        """(principal or None for invalid, whether fresh) of a token seen before; None if never
        seen."""
        now = time.monotonic()
        hit = self._valid.get(token)
        if hit is not None:
            return hit[1], now - hit[0] < self.ttl_s
        seen = self._invalid.get(token)
        if seen is not None and now - seen < self.ttl_s:
            return None, True
        return None

    def put(self, token: str, principal: Principal | None) -> None:
        now = time.monotonic()
        if principal is None:
            self._valid.pop(token, None)
            if len(self._invalid) >= self.max_invalid:
                self._invalid.clear()
            self._invalid[token] = now
        else:
            self._invalid.pop(token, None)
            self._valid[token] = (now, principal)

    def checked(self, token: str) -> None:
        """A re-check that could not reach the database: keep the answer, ask again after
        `ttl_s`."""
        hit = self._valid.get(token)
        if hit is not None:
            self._valid[token] = (time.monotonic(), hit[1])

    def known(self, token: str) -> Principal | None:
        """The principal of a token the daemon knows to be valid (freshly or not); None
        otherwise."""
        hit = self._valid.get(token)
        return None if hit is None else hit[1]

    def clear(self) -> None:
        self._valid.clear()
        self._invalid.clear()


class FailedTokens:
    """Unknown tokens per client address: `burst` may fail in a row, then one more every `every_s`
    seconds.

    A token bucket per address; only a failure takes from it, so a lab whose LIMS retries now and
    then is slowed at worst, and a token the daemon knows passes whatever its address's bucket
    holds."""

    def __init__(self, burst: int = 20, every_s: float = 2.0, max_addresses: int = 10_000) -> None:
        self.burst = burst
        self.every_s = every_s
        self.max_addresses = max_addresses
        # address -> (failures it may still make, when)
        self._buckets: dict[str, tuple[float, float]] = {}
        self.refused = 0

    def _level(self, address: str, now: float) -> float:
        left, at = self._buckets.get(address, (float(self.burst), now))
        return min(float(self.burst), left + (now - at) / self.every_s)

    def retry_after_s(self, address: str) -> int | None:
        """Seconds until this address may try an unknown token again; None when it may now."""
        level = self._level(address, time.monotonic())
        if level >= 1.0:
            return None
        self.refused += 1
        return max(1, math.ceil((1.0 - level) * self.every_s))

    def failed(self, address: str) -> None:
        now = time.monotonic()
        if len(self._buckets) >= self.max_addresses:  # forget the addresses that are full again
            self._buckets = {
                other: bucket
                for other, bucket in self._buckets.items()
                if self._level(other, now) < self.burst
            }
            if len(self._buckets) >= self.max_addresses:
                self._buckets.clear()
        self._buckets[address] = (max(0.0, self._level(address, now) - 1.0), now)


class TokenChecks:
    """The principal of a presented token: from the cache, else from the database off the loop."""

    def __init__(
        self,
        authenticate: Callable[[str], Principal | None],
        calls: DatabaseCalls,
        database: DatabaseState | None = None,
        cache: TokenCache | None = None,
        throttle: FailedTokens | None = None,
    ) -> None:
        self._authenticate = authenticate  # blocking: the token's row in the database
        self.calls = calls
        self.database = database
        self.cache = cache or TokenCache()
        self.throttle = throttle or FailedTokens()
        # one database question per token at a time
        self._asking: dict[str, asyncio.Future[Principal | None]] = {}
        self._rechecks: set[asyncio.Task[None]] = set()

    async def principal(self, token: str | None, address: str) -> Principal:
        """The token's principal, or ProblemError: 401 (missing, unknown, revoked), 429 (this
        address failed too often), 503 (the database did not answer in time)."""
        if not token:
            raise ProblemError(
                401,
                "Unauthorized",
                "this route needs a token: send 'Authorization: Bearer <token>'"
                " (tiltlab token create, or the admin token file in the data directory)",
                headers=UNAUTHORIZED,
            )
        seen = self.cache.answer(token)
        if seen is not None and seen[0] is not None:
            if not seen[1]:
                self._recheck(token)
            return seen[0]
        wait_s = self.throttle.retry_after_s(address)
        if wait_s is not None:
            raise ProblemError(
                429,
                "Too many unknown tokens",
                f"too many requests from {address} came with an unknown or revoked token; try "
                "again in"
                f" {wait_s} s (TILTLAB_FAILED_TOKENS_BURST, TILTLAB_FAILED_TOKENS_EVERY_S)",
                headers={"Retry-After": str(wait_s)},
            )
        principal = None if seen is not None else await self._ask(token)
        if principal is None:
            self.throttle.failed(address)
            raise ProblemError(
                401, "Unauthorized", "the token is unknown or revoked", headers=INVALID
            )
        return principal

    def known(self, token: str) -> Principal | None:
        """Without waiting: the principal of a token the daemon knows to be valid (re-checked in the
        background when its answer is old), else None (only the database can say)."""
        seen = self.cache.answer(token)
        if seen is None or seen[0] is None:
            return None
        if not seen[1]:
            self._recheck(token)
        return seen[0]

    async def _ask(self, token: str) -> Principal | None:
        asking = self._asking.get(token)
        if asking is None:
            asking = self._asking[token] = asyncio.ensure_future(self._query(token))
            asking.add_done_callback(lambda _: self._asking.pop(token, None))
        return await asyncio.shield(asking)

    async def _query(self, token: str) -> Principal | None:
        try:
            principal = await self.calls.run(self._authenticate, token)
        except DatabaseSlow:
            raise
        except Exception as exc:
            if not unreachable(exc):
                raise
            if self.database is not None:
                self.database.away(exc)
            raise DatabaseSlow(
                f"the database {self.calls.where} does not answer ({type(exc).__name__}), so the"
                " token could not be checked; ask again once it answers (GET /health says when)"
            ) from None
        if self.database is not None:
            self.database.back()
        self.cache.put(token, principal)
        return principal

    def _recheck(self, token: str) -> None:
        if token in self._asking:
            return
        self.cache.checked(token)  # one re-check per ttl_s, whatever it finds

        async def recheck() -> None:
            try:
                await self._ask(token)
            except Exception as exc:  # noqa: BLE001 - the last answer stands until the database answers
                log.info(
                    "a known token could not be re-checked (%s); its last answer stands",
                    type(exc).__name__,
                )

        task = asyncio.get_running_loop().create_task(recheck())
        self._rechecks.add(task)
        task.add_done_callback(self._rechecks.discard)


def token_checks(app: Any) -> TokenChecks:
    """The application's token checks (made on first use where the lifespan made none)."""
    checks = getattr(app.state, "token_checks", None)
    if not isinstance(checks, TokenChecks):
        calls = getattr(app.state, "db_calls", None) or DatabaseCalls("the database")
        checks = app.state.token_checks = TokenChecks(
            app.state.store.tokens.authenticate, calls, getattr(app.state, "database", None)
        )
    return checks


class Authentication:
    """The token checked in front of the routing table, for every HTTP path but the public ones.

    The request's principal goes on in its scope (`PRINCIPAL`) for the routes' scope checks; the
    request's database pool is made the one its database calls use."""

    def __init__(self, app: ASGIApp, state_of: Any) -> None:
        self.app = app
        self._state_of = state_of  # the FastAPI application, whose state the lifespan fills

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        state = self._state_of.state
        use_calls(getattr(state, "db_calls", None))
        settings = getattr(state, "settings", None)
        if scope["type"] != "http" or is_public(scope["path"]) or settings is None:
            await self.app(scope, receive, send)
            return
        if settings.auth == "none":
            principal = EVERYONE
        else:
            try:
                principal = await token_checks(self._state_of).principal(
                    bearer_of(scope["headers"]), client_address(scope)
                )
            except ProblemError as exc:
                response = problem(
                    exc.status, exc.title, exc.detail, instance=scope["path"], **exc.extra
                )
                response.headers.update(exc.headers or {})
                await response(scope, receive, send)
                return
        scope[PRINCIPAL] = principal
        await self.app(scope, receive, send)


def requires(scope: str) -> Callable[..., Awaitable[Principal]]:
    """A dependency giving the request's principal, refusing it without `scope`."""
    assert scope in SCOPES

    async def dependency(
        request: Request, _: Annotated[HTTPAuthorizationCredentials | None, Depends(BEARER)]
    ) -> Principal:
        principal = request.scope.get(PRINCIPAL)
        if not isinstance(principal, Principal):  # an application without the middleware in front
            settings = request.app.state.settings
            principal = (
                EVERYONE
                if settings.auth == "none"
                else await token_checks(request.app).principal(
                    bearer_of(request.scope["headers"]), client_address(request.scope)
                )
            )
        if not principal.may(scope):
            raise ProblemError(
                403,
                "Forbidden",
                f"the token {principal.name!r} lacks the scope {scope!r}"
                f" (it has {', '.join(sorted(principal.scopes))})",
            )
        return principal

    return dependency


SUBPROTOCOL_PREFIX = "bearer."


def websocket_subprotocol(websocket: WebSocket) -> str | None:
    """The `bearer.<token>` subprotocol the client offered, if any (the accept must name it
    back)."""
    for offered in websocket.scope.get("subprotocols") or ():
        if offered.startswith(SUBPROTOCOL_PREFIX):
            return str(offered)
    return None


def websocket_token(websocket: WebSocket) -> str | None:
    """A WebSocket's token: from its `bearer.<token>` subprotocol, else its `token` query
    parameter."""
    offered = websocket_subprotocol(websocket)
    if offered is not None:
        return offered.removeprefix(SUBPROTOCOL_PREFIX)
    return websocket.query_params.get("token")


async def websocket_principal(websocket: WebSocket, scope: str = "read") -> Principal:
    """The principal of a WebSocket from its token (subprotocol or query), or ProblemError saying
    why it may not connect (401, 403, 429, 503: the stream closes with a reason).

    Asked again while a stream is open, so a revoked token's streams end (from the token cache:
    no database query on the event loop, at most one in the background per token every few
    seconds)."""
    if websocket.app.state.settings.auth == "none":
        return EVERYONE
    principal = await token_checks(websocket.app).principal(
        websocket_token(websocket), client_address(websocket.scope)
    )
    if not principal.may(scope):
        raise ProblemError(
            403, "Forbidden", f"the token {principal.name!r} lacks the scope {scope!r}"
        )
    return principal


Reader = Annotated[Principal, Depends(requires("read"))]
Operator = Annotated[Principal, Depends(requires("operate"))]
Admin = Annotated[Principal, Depends(requires("admin"))]
