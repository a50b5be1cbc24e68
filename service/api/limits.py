"""Limits at the daemon's edge: the request-body limit (a pure ASGI middleware below FastAPI) and
the send buffer of every connection (an option of the listening socket).

A body over the limit is refused (413, problem+json) from its declared `Content-Length` before a
byte of it is read, and a body sent without a length (chunked) is counted while it arrives and
refused as soon as it passes the limit. Both happen before a route, its dependencies or the token
check run, so a stranger without a token cannot make the daemon hold a large body in memory.
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
# uvicorn's WebSocket implementation: websockets' sans-I/O protocol writes each message straight to the
# connection and waits only while the connection's write buffer is above its high-water mark (64 kB);
# about a quarter less CPU per stream message than the older asyncio protocol.
WEBSOCKET_IMPLEMENTATION = "websockets-sansio"
# The most the daemon holds for one stream client that has stopped reading before its sends wait.
STREAM_HELD_BYTES = 2 * SEND_BUFFER_BYTES + SERVER_WRITE_BUFFER_BYTES


def bound_send_buffer(sock: socket.socket) -> None:
    """Fix the send buffer of the connections a listening socket will accept (they inherit it).

    Set on the listening socket before it listens, so no server internals are touched; a 64 kB
    window still carries tens of MB/s on a lab network."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)


def _too_large(path: str, max_bytes: int) -> tuple[Message, Message]:
    body = json.dumps({"type": "about:blank", "title": "Content Too Large", "status": 413,
                       "detail": f"the request body is larger than {max_bytes} bytes (TILTLAB_MAX_BODY_BYTES)",
                       "instance": path}).encode()
    start: Message = {"type": "http.response.start", "status": 413,
                      "headers": [(b"content-type", PROBLEM.encode()), (b"content-length", str(len(body)).encode()),
                                  (b"connection", b"close")]}
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
                    return {"type": "http.disconnect"}  # the route stops reading as if the client had gone
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
                raise  # a failure of the route itself; once refused, what the route made of it is moot


def _content_length(scope: Scope) -> int | None:
    headers: Any = scope.get("headers") or ()
    for name, value in headers:
        if name == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None
    return None
