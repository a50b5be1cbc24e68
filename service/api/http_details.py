"""HTTP details every route gets without saying so: HEAD wherever GET is served, and a 405 answer
that carries `Allow` with every method the path takes (not only the first route that matched).

Written as plain ASGI middleware over the finished routing table, so routers added later by any
domain get the same behaviour.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send


def allowed_methods(routes: Iterable[Any], scope: Scope) -> list[str]:
    """Every method some route serves at this path; HEAD wherever GET is, OPTIONS never (no CORS
    here)."""
    methods: set[str] = set()
    _collect(routes, {**scope, "method": "GET"}, methods)
    if "GET" in methods:
        methods.add("HEAD")
    return sorted(methods)


def _collect(routes: Iterable[Any], scope: Scope, methods: set[str]) -> None:
    for route in routes:
        match, child = route.matches(scope)
        if match == Match.NONE:
            continue
        route_methods = getattr(route, "methods", None)
        if route_methods:
            methods.update(route_methods)
            continue
        contexts = getattr(route, "effective_route_contexts", None)  # FastAPI's included routers
        if callable(contexts):
            _collect(contexts(), scope, methods)
            continue
        inner = getattr(route, "routes", None)  # mounts and plain sub-routers: look inside
        if inner:
            _collect(inner, {**scope, **child}, methods)


class HttpDetails:
    """HEAD answered as GET without a body; `Allow` on every 405."""

    def __init__(self, app: ASGIApp, routes_of: Any) -> None:
        self.app = app
        # the FastAPI application, whose routes are read at request time
        self._routes_of = routes_of

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        head = scope["method"] == "HEAD"
        if head:
            scope = {**scope, "method": "GET"}
        finished = False

        async def send_detailed(message: Message) -> None:
            nonlocal finished
            if finished:
                return  # a HEAD answer is complete once its headers are out
            if message["type"] == "http.response.start" and message["status"] == 405:
                allow = ", ".join(allowed_methods(self._routes_of.router.routes, scope))
                headers = [
                    (name, value)
                    for name, value in message.get("headers", [])
                    if name.lower() != b"allow"
                ]
                message = {**message, "headers": [*headers, (b"allow", allow.encode("latin-1"))]}
            await send(message)
            if head and message["type"] == "http.response.start":
                await send({"type": "http.response.body", "body": b"", "more_body": False})
                finished = True

        async def receive_detailed() -> Message:
            if finished:  # tell a streaming endpoint that the HEAD client has what it asked for
                return {"type": "http.disconnect"}
            return await receive()

        await self.app(scope, receive_detailed if head else receive, send_detailed)


def install(app: Any) -> None:
    app.add_middleware(HttpDetails, routes_of=app)
