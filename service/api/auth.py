"""Bearer tokens and scopes on every route but /health, /ready and the dashboard's files.

`Authorization: Bearer <token>` on HTTP. On WebSockets (browsers cannot set headers there) the
subprotocol `bearer.<token>` (`Sec-WebSocket-Protocol`, kept out of URLs and so out of logs) or the
`token` query parameter. 401 without a valid token, 403 without the scope the route needs.
"""

from __future__ import annotations

import ipaddress
import time
from collections.abc import Awaitable, Callable
from typing import Annotated, Any

from fastapi import Depends, Request, WebSocket
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.api.problems import ProblemError
from service.storage.outage import unreachable
from service.storage.tokens import SCOPES, Principal

EVERYONE = Principal("anonymous (authentication off)", frozenset(SCOPES))

# The OpenAPI document's security scheme (`bearerAuth`); the header itself is read by `_bearer` so that a
# missing or malformed one is a 401 problem, not FastAPI's own answer.
BEARER = HTTPBearer(scheme_name="bearerAuth", auto_error=False,
                    description="a token of `tiltlab token create` (or the admin token file); scopes read, operate, admin")


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _bearer(request: Request) -> str | None:
    header = request.headers.get("authorization", "")
    scheme, _, value = header.partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        return value.strip()
    return None


def _principal(app: Any, token: str | None) -> Principal:
    if app.state.settings.auth == "none":
        return EVERYONE
    if not token:
        raise ProblemError(401, "Unauthorized", "this route needs a token: send 'Authorization: Bearer <token>'"
                           " (tiltlab token create, or the admin token file in the data directory)",
                           headers={"WWW-Authenticate": 'Bearer realm="tiltlab"'})
    cache = getattr(app.state, "token_cache", None)
    if cache is None:
        cache = app.state.token_cache = TokenCache()
    principal = cache.lookup(token, app.state.store.tokens.authenticate)
    if principal is None:
        raise ProblemError(401, "Unauthorized", "the token is unknown or revoked",
                           headers={"WWW-Authenticate": 'Bearer realm="tiltlab", error="invalid_token"'})
    return principal


class TokenCache:
    """Recently seen tokens, so a busy reader costs no database query per request.

    An entry lives `ttl_s` seconds; a revocation through this daemon clears the cache at once, one
    made by `tiltlab token revoke` elsewhere takes effect within `ttl_s`. While the database is away
    a token seen before keeps its last answer (asked again every `ttl_s`): the daemon goes on serving
    its benches to the people it knew, and no revocation can be written meanwhile anyway.
    """

    def __init__(self, ttl_s: float = 5.0) -> None:
        self.ttl_s = ttl_s
        self._seen: dict[str, tuple[float, Principal | None]] = {}

    def lookup(self, token: str, authenticate: Callable[[str], Principal | None]) -> Principal | None:
        now = time.monotonic()
        hit = self._seen.get(token)
        if hit is not None and now - hit[0] < self.ttl_s:
            return hit[1]
        try:
            principal = authenticate(token)
        except Exception as exc:
            if hit is None or not unreachable(exc):
                raise
            self._seen[token] = (now, hit[1])
            return hit[1]
        if len(self._seen) > 10_000:
            self._seen.clear()
        self._seen[token] = (now, principal)
        return principal

    def known(self, token: str) -> Principal | None:
        """The principal of a token seen within `ttl_s` and then valid; None where only the database can say."""
        hit = self._seen.get(token)
        if hit is None or time.monotonic() - hit[0] >= self.ttl_s:
            return None
        return hit[1]

    def clear(self) -> None:
        self._seen.clear()


def requires(scope: str) -> Callable[..., Awaitable[Principal]]:
    """A dependency giving the request's principal, refusing it without `scope`."""
    assert scope in SCOPES

    async def dependency(request: Request,
                         _: Annotated[HTTPAuthorizationCredentials | None, Depends(BEARER)]) -> Principal:
        principal = _principal(request.app, _bearer(request))
        if not principal.may(scope):
            raise ProblemError(403, "Forbidden", f"the token {principal.name!r} lacks the scope {scope!r}"
                               f" (it has {', '.join(sorted(principal.scopes))})")
        return principal

    return dependency


SUBPROTOCOL_PREFIX = "bearer."


def websocket_subprotocol(websocket: WebSocket) -> str | None:
    """The `bearer.<token>` subprotocol the client offered, if any (the accept must name it back)."""
    for offered in websocket.scope.get("subprotocols") or ():
        if offered.startswith(SUBPROTOCOL_PREFIX):
            return str(offered)
    return None


def websocket_token(websocket: WebSocket) -> str | None:
    """A WebSocket's token: from its `bearer.<token>` subprotocol, else its `token` query parameter."""
    offered = websocket_subprotocol(websocket)
    if offered is not None:
        return offered.removeprefix(SUBPROTOCOL_PREFIX)
    return websocket.query_params.get("token")


def websocket_principal(websocket: WebSocket, scope: str = "read") -> Principal | None:
    """The principal of a WebSocket from its token (subprotocol or query); None if it may not connect.

    Asked again while a stream is open, so a revoked token's streams end (the token cache keeps
    this to one database query per token every few seconds)."""
    try:
        principal = _principal(websocket.app, websocket_token(websocket))
    except ProblemError:
        return None
    return principal if principal.may(scope) else None


Reader = Annotated[Principal, Depends(requires("read"))]
Operator = Annotated[Principal, Depends(requires("operate"))]
Admin = Annotated[Principal, Depends(requires("admin"))]
