"""Limits at the daemon's edge: the request-body limit (a pure ASGI middleware below FastAPI) and
the send buffer of every connection (an option of the listening socket).

A body over the limit is refused (413, problem+json) from its declared `Content-Length` before a
byte of it is read. A body sent without a length (chunked) is read here, up to the limit, before the
request goes on, and refused as soon as it passes the limit: on every route, whether or not the
route takes a body (the server would otherwise read and drop the rest of it after the route's
answer, a gigabyte as readily as a byte). Both happen before a route, its dependencies or the token
check run, so a stranger without a token cannot make the daemon hold more than the limit in memory.
"""

from __future__ import annotations

import json
import socket
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.problems import PROBLEM

# The kernel send buffer of each connection, fixed (not left to autotuning, which grows it to 4 MB):
# what a stream client that stopped reading can have waiting in the daemon's kernel. Linux doubles
# the value asked for (its bookkeeping), so a connection holds at most 64 kB there; the server's
# own write buffer holds at most 64 kB more before a send waits.
SEND_BUFFER_BYTES = 32_768
SERVER_WRITE_BUFFER_BYTES = 65_536  # the ASGI server's WebSocket write buffer (its high-water mark)
# uvicorn's WebSocket implementation: websockets' sans-I/O protocol writes each message straight to
# the connection and waits only while the connection's write buffer is above its high-water mark (64
# kB); about a quarter less CPU per stream message than the older asyncio protocol.
WEBSOCKET_IMPLEMENTATION = "websockets-sansio"
# The most the daemon holds for one stream client that has stopped reading before its sends wait.
STREAM_HELD_BYTES = 2 * SEND_BUFFER_BYTES + SERVER_WRITE_BUFFER_BYTES


def bound_send_buffer(sock: socket.socket) -> None:
    """Fix the send buffer of the connections a listening socket will accept (they inherit it).

    Set on the listening socket before it listens, so no server internals are touched; a 64 kB
    window still carries tens of MB/s on a lab network."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)


def _too_large(path: str, max_bytes: int) -> tuple[Message, Message]:
    body = json.dumps(
        {
            "type": "about:blank",
            "title": "Content Too Large",
            "status": 413,
            "detail": f"the request body is larger than {max_bytes} bytes (TILTLAB_MAX_BODY_BYTES)",
            "instance": path,
        }
    ).encode()
    start: Message = {
        "type": "http.response.start",
        "status": 413,
        "headers": [
            (b"content-type", PROBLEM.encode()),
            (b"content-length", str(len(body)).encode()),
            (b"connection", b"close"),
        ],
    }
    return start, {"type": "http.response.body", "body": body}


class BodySizeLimit:
    """Refuse HTTP request bodies over `max_bytes` (413) before they are read."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = _content_length(scope)
        if declared is not None and declared > self.max_bytes:
            for message in _too_large(scope.get("path", ""), self.max_bytes):
                await send(message)
            return
        if _chunked(scope):
            body = await _read_up_to(receive, self.max_bytes)
            if body is None:
                for message in _too_large(scope.get("path", ""), self.max_bytes):
                    await send(message)
                return
            receive = _replay(body, receive)
        received = 0
        answered = False  # the 413 went out: the application's own answer is not sent
        response_started = False

        async def counting_receive() -> Message:
            nonlocal received, answered
            if answered:
                return {"type": "http.disconnect"}
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    if not response_started:
                        for m in _too_large(scope.get("path", ""), self.max_bytes):
                            await send(m)
                    answered = True
                    # the route stops reading as if the client had gone
                    return {"type": "http.disconnect"}
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal response_started
            if answered:
                return
            if message["type"] == "http.response.start":
                response_started = True
            await send(message)

        try:
            await self.app(scope, counting_receive, guarded_send)
        except Exception:
            if not answered:
                # a failure of the route itself; once refused, what the route made of it is moot
                raise


def _chunked(scope: Scope) -> bool:
    """A body sent without a declared length (Transfer-Encoding: chunked)."""
    headers: Any = scope.get("headers") or ()
    return any(
        name == b"transfer-encoding" and b"chunked" in value.lower() for name, value in headers
    )


async def _read_up_to(receive: Receive, max_bytes: int) -> bytes | None:
    """The whole body if it is at most `max_bytes`, else None as soon as it passes them (the rest
    unread)."""
    chunks: list[bytes] = []
    size = 0
    while True:
        message = await receive()
        if message["type"] != "http.request":
            break
        chunk = message.get("body", b"")
        size += len(chunk)
        if size > max_bytes:
            return None
        chunks.append(chunk)
        if not message.get("more_body", False):
            break
    return b"".join(chunks)


def _replay(body: bytes, receive: Receive) -> Receive:
    """The body read here, handed on as if it came now; then the client's own messages (a
    disconnect)."""
    sent = False

    async def again() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return again


def _content_length(scope: Scope) -> int | None:
    headers: Any = scope.get("headers") or ()
    for name, value in headers:
        if name == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None
    return None
