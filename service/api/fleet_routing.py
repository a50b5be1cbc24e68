"""Requests for another node's bench, carried to that node and answered as if asked there.

A pure ASGI middleware in front of the routers: a bench command (`POST /calibrations`,
`/stage/*`) or a bench read (`GET /tilt`, `GET /devices`) naming a bench of another live node
goes to its owner over the broker (request/reply) with the caller's own headers, so the owner
checks the same token against the same database and audits the same person. The owner runs it
through its own application, and the answer comes back unchanged except that `GET /tilt` gains
the `node` it came from and its `age_s` grows by the round trip. Everything else passes through.
"""

from __future__ import annotations

import json
from urllib.parse import parse_qs

import httpx
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api import problems
from service.fleet.node import Fleet, FleetUnavailable, ForwardedAnswer, ForwardedRequest

BENCH_READS = frozenset({"/tilt", "/devices"})
BENCH_COMMANDS = frozenset(
    {"/calibrations", "/stage/move", "/stage/level", "/stage/stop", "/stage/home"}
)
FORWARDED_HEADERS = ("authorization", "content-type", "idempotency-key", "accept")
ANSWER_HEADERS = ("content-type", "location")
MAX_FORWARDED_BODY = 1 << 20


class FleetRouting:
    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        fleet = _fleet_to_route(scope)
        if fleet is None:
            await self.app(scope, receive, send)
            return
        path, method = scope.get("path", ""), scope.get("method", "")
        query = scope.get("query_string", b"").decode("latin-1")
        bench = (parse_qs(query).get("bench") or [None])[0]
        body = b""
        if method == "POST":
            body = await _read_body(receive)
            if bench is None:
                bench = _bench_of(body)
        if not fleet.is_remote(bench):
            await self.app(scope, _replay(body, receive), send)
            return
        assert bench is not None
        request = _forwarded_request(scope, query, body)
        try:
            answer, round_trip_s = await fleet.forward(bench, request)
        except FleetUnavailable as exc:
            response = problems.problem(
                503, "Bench's node not reachable", str(exc), instance=path, field="bench"
            )
            await response(scope, receive, send)
            return
        content = answer.get("body", "").encode()
        if path == "/tilt" and answer.get("status") == 200:
            content = _tilt_via(content, fleet.remote[bench].node, round_trip_s)
        await _send_answer(send, answer, content)


def _fleet_to_route(scope: Scope) -> Fleet | None:
    """The fleet, when the request is a bench read or command it may carry to another node; None
    when the request is this node's own to answer."""
    fleet: Fleet | None = getattr(scope["app"].state, "fleet", None) if "app" in scope else None
    path, method = scope.get("path", ""), scope.get("method", "")
    if (
        scope["type"] != "http"
        or fleet is None
        or not (
            (method == "GET" and path in BENCH_READS)
            or (method == "POST" and path in BENCH_COMMANDS)
        )
    ):
        return None
    return fleet


def _forwarded_request(scope: Scope, query: str, body: bytes) -> ForwardedRequest:
    """The request as the bench's owner gets it: the caller's own headers (the token, the
    Idempotency-Key) with it."""
    headers = {name.decode("latin-1"): value.decode("latin-1") for name, value in scope["headers"]}
    return {
        "method": scope.get("method", ""),
        "path": scope.get("path", ""),
        "query": query,
        "body": body.decode("utf-8", "replace"),
        "headers": {k: headers[k] for k in FORWARDED_HEADERS if k in headers},
    }


async def _send_answer(send: Send, answer: ForwardedAnswer, content: bytes) -> None:
    """The owner's answer passed on: its status, the headers that describe its content, the
    content."""
    out_headers = [
        (name.encode(), str(value).encode())
        for name, value in answer.get("headers", {}).items()
        if name in ANSWER_HEADERS
    ]
    out_headers.append((b"content-length", str(len(content)).encode()))
    await send(
        {
            "type": "http.response.start",
            "status": int(answer.get("status", 502)),
            "headers": out_headers,
        }
    )
    await send({"type": "http.response.body", "body": content})


def _tilt_via(content: bytes, node: str, round_trip_s: float) -> bytes:
    """The owner's /tilt answer, honest about the path: from which node, and older by the round
    trip."""
    tilt = json.loads(content)
    tilt["node"] = node
    if isinstance(tilt.get("age_s"), int | float):
        tilt["age_s"] = tilt["age_s"] + round_trip_s
    return json.dumps(tilt).encode()


async def _read_body(receive: Receive) -> bytes:
    chunks: list[bytes] = []
    size = 0
    while True:
        message = await receive()
        if message["type"] != "http.request":
            break
        chunk = message.get("body", b"")
        size += len(chunk)
        # far beyond any bench command; the routers refuse it with their own rules
        if size > MAX_FORWARDED_BODY:
            chunks.append(chunk)
            break
        chunks.append(chunk)
        if not message.get("more_body", False):
            break
    return b"".join(chunks)


def _bench_of(body: bytes) -> str | None:
    try:
        doc: object = json.loads(body)
    except ValueError:
        return None
    bench = doc.get("bench") if isinstance(doc, dict) else None
    return bench if isinstance(bench, str) else None


def _replay(body: bytes, receive: Receive) -> Receive:
    """The body already read, handed to the application as if it came now; then the client's own
    messages."""
    sent = False

    async def again() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return again


async def run_forwarded(app: ASGIApp, request: ForwardedRequest) -> ForwardedAnswer:
    """On the bench's owner: a request another node carried here, run through this daemon's own
    application."""
    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(transport=transport, base_url="http://fleet.invalid") as client:
        url = request["path"] + (f"?{request['query']}" if request.get("query") else "")
        answer = await client.request(
            request["method"],
            url,
            headers=request.get("headers", {}),
            content=request.get("body", "").encode(),
        )
    return {
        "status": answer.status_code,
        "body": answer.text,
        "headers": {k: answer.headers[k] for k in ANSWER_HEADERS if k in answer.headers},
    }
