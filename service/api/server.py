"""The daemon's HTTP server: uvicorn, with the limits a request must meet before it is parsed.

uvicorn takes the protocol it runs per connection as a setting (`http=`, `ws=`: a protocol class);
these are its own HTTP (httptools) and WebSocket (websockets, sans-I/O) protocols with what they
lack for a daemon on a lab network:

* **The request head is bounded before it is parsed**: the bytes of a request line and headers
  (`TILTLAB_MAX_HEADER_BYTES`) and the number of header lines (`TILTLAB_MAX_HEADERS`) are counted
  as they arrive, and a head past either limit is answered 431 and the connection closed; the
  parser (which would gather a header of any length in memory) never sees it.
* **A head must arrive within `TILTLAB_HEADER_TIMEOUT_S`** of its first byte (of the connection,
  for a client that says nothing): one that trickles in (slowloris) is answered 408 and closed.
  Between requests uvicorn's own keep-alive timeout (5 s) closes an idle connection.
* **Connections per client address** (`TILTLAB_MAX_CONNECTIONS_PER_CLIENT`), HTTP and WebSocket
  together: one more is answered 429 with `Retry-After` and closed at once.
* **A closed connection is closed**: once the daemon closes a connection (a stream client dropped
  for not reading, an answer the client does not read), it waits `CLOSE_GRACE_S` for what is still
  buffered to go out, then drops the connection (a TCP reset) rather than keep it open for as long
  as the peer keeps its window shut.
"""

from __future__ import annotations

import asyncio
import json
from typing import Any

from uvicorn.config import Config
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from uvicorn.server import ServerState

from service.api.problems import PROBLEM

# after the daemon closes a connection: how long its buffered bytes may take to leave
CLOSE_GRACE_S = 5.0
RETRY_AFTER_S = 5
HEAD_END = b"\r\n\r\n"


def _answer(
    status: int, reason: str, title: str, detail: str, headers: dict[str, str] | None = None
) -> bytes:
    """A complete HTTP/1.1 problem answer that closes the connection (written before or instead of a
    request)."""
    body = json.dumps(
        {"type": "about:blank", "title": title, "status": status, "detail": detail}
    ).encode()
    lines = [
        f"HTTP/1.1 {status} {reason}",
        f"content-type: {PROBLEM}",
        f"content-length: {len(body)}",
        "connection: close",
        *(f"{name}: {value}" for name, value in (headers or {}).items()),
    ]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + body


class ClosingTransport:
    """A connection's transport whose `close()` becomes an abort once `grace_s` has passed without
    the peer taking what is still buffered (asyncio's close waits for the buffer to drain, for ever
    if the peer never reads). Everything else is the transport's own."""

    def __init__(
        self, transport: asyncio.Transport, loop: asyncio.AbstractEventLoop, grace_s: float
    ) -> None:
        self._transport = transport
        self._loop = loop
        self._grace_s = grace_s
        self._abort: asyncio.TimerHandle | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self._transport, name)

    @property
    def real(self) -> asyncio.Transport:
        return self._transport

    def close(self) -> None:
        self._transport.close()
        if self._abort is None and self._transport.get_write_buffer_size() > 0:
            self._abort = self._loop.call_later(self._grace_s, self._transport.abort)

    def lost(self) -> None:
        if self._abort is not None:
            self._abort.cancel()
            self._abort = None


class ClientConnections:
    """The open connections of each client address (HTTP and WebSocket alike; a connection counts
    until it is closing)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._open: dict[str, set[asyncio.BaseTransport]] = {}
        self.refused = 0

    def admit(self, address: str, transport: asyncio.BaseTransport) -> bool:
        mine = self._open.setdefault(address, set())
        for t in [t for t in mine if t.is_closing()]:
            mine.discard(t)
        if len(mine) >= self.limit:
            self.refused += 1
            return False
        mine.add(transport)
        return True

    def release(self, address: str, transport: asyncio.BaseTransport) -> None:
        mine = self._open.get(address)
        if mine is not None:
            mine.discard(transport)
            if not mine:
                del self._open[address]

    def count(self, address: str) -> int:
        return sum(1 for t in self._open.get(address, ()) if not t.is_closing())


class BoundedHttpProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with the head bounded in size, line count and time, and
    connections counted per client address (the limits are set on the subclass `protocols()`
    makes)."""

    max_head_bytes = 32_768
    max_head_lines = 101  # the request line and 100 headers
    head_timeout_s = 10.0
    connections_per_client: ClientConnections = ClientConnections(64)

    def __init__(
        self,
        config: Config,
        server_state: ServerState,
        app_state: dict[str, object],
        _loop: asyncio.AbstractEventLoop | None = None,
    ) -> None:
        super().__init__(config, server_state, app_state, _loop)
        self._in_head = True
        self._head_bytes = 0
        self._head_lines = 0
        self._tail = b""  # the last bytes of the head so far: its end may straddle two reads
        self._head_timer: asyncio.TimerHandle | None = None
        self._refused = False
        self._address = ""
        self._counted: asyncio.BaseTransport | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        closing = ClosingTransport(transport, self.loop, CLOSE_GRACE_S)
        super().connection_made(closing)  # type: ignore[arg-type]
        self._address = self.client[0] if self.client else "unknown"
        if not self.connections_per_client.admit(self._address, transport):
            self._refuse(
                429,
                "Too Many Requests",
                "Too many connections",
                f"{self._address} has {self.connections_per_client.limit} connections open to the "
                "daemon"
                " already (TILTLAB_MAX_CONNECTIONS_PER_CLIENT); close some, or try again later",
                {"Retry-After": str(RETRY_AFTER_S)},
            )
            return
        self._counted = transport
        self._arm_head_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm_head_timer()
        # (an upgraded connection is the WebSocket protocol's to release)
        if self._counted is not None:
            self.connections_per_client.release(self._address, self._counted)
        if isinstance(self.transport, ClosingTransport):
            self.transport.lost()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._refused:
            return
        if self._in_head:
            if self._head_timer is None:
                self._arm_head_timer()
            if not self._count_head(data):
                return
        super().data_received(data)

    def _count_head(self, data: bytes) -> bool:
        """Count the head's bytes and lines in this read; False (and the connection refused) past a
        limit."""
        seen = self._tail + data
        end = seen.find(HEAD_END)
        part = data if end < 0 else data[: max(0, end + len(HEAD_END) - len(self._tail))]
        self._head_bytes += len(part)
        self._head_lines += part.count(b"\n")
        self._tail = seen[-(len(HEAD_END) - 1) :]
        if self._head_bytes > self.max_head_bytes or self._head_lines > self.max_head_lines + 1:
            what = (
                f"{self._head_lines - 2:,} header lines or more, more than the "
                f"{self.max_head_lines - 1:,} taken (TILTLAB_MAX_HEADERS)"
                if self._head_lines > self.max_head_lines + 1
                else f"{self._head_bytes:,} bytes or more, more than the {self.max_head_bytes:,} "
                "taken (TILTLAB_MAX_HEADER_BYTES)"
            )
            self._refuse(
                431,
                "Request Header Fields Too Large",
                "Request head too large",
                f"the request line and headers are {what}; nothing of it was read further",
            )
            return False
        if end >= 0:
            self._end_head()
        return True

    def _end_head(self) -> None:
        self._in_head = False
        self._head_bytes = self._head_lines = 0
        self._tail = b""
        self._disarm_head_timer()

    def on_message_complete(self) -> None:
        super().on_message_complete()
        # what comes next is the next request's head (its timer starts with its first byte)
        self._in_head = True

    def _arm_head_timer(self) -> None:
        self._disarm_head_timer()
        self._head_timer = self.loop.call_later(self.head_timeout_s, self._head_too_slow)

    def _disarm_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_too_slow(self) -> None:
        self._head_timer = None
        if not self._in_head or self._refused or self.transport.is_closing():
            return
        # an answer is still being written
        if self.cycle is not None and not self.cycle.response_complete:
            self._arm_head_timer()
            return
        self._refuse(
            408,
            "Request Timeout",
            "Request head too slow",
            f"the request line and headers did not arrive within {self.head_timeout_s:g} s"
            " (TILTLAB_HEADER_TIMEOUT_S)",
        )

    def _refuse(
        self,
        status: int,
        reason: str,
        title: str,
        detail: str,
        headers: dict[str, str] | None = None,
    ) -> None:
        self._refused = True
        self._disarm_head_timer()
        if self.cycle is not None and not self.cycle.response_complete:
            # an answer is being written: the connection cannot carry another
            self.transport.abort()
            return
        self.transport.write(_answer(status, reason, title, detail, headers))
        self.transport.close()

    def handle_websocket_upgrade(self) -> None:
        # the WebSocket protocol gets the connection's own transport (it wraps it again for its
        # closes)
        if isinstance(self.transport, ClosingTransport):
            self.transport = self.transport.real
        super().handle_websocket_upgrade()


class BoundedWebSocketProtocol(WebSocketsSansIOProtocol):
    """uvicorn's sans-I/O WebSocket protocol whose closes end the TCP connection within
    `CLOSE_GRACE_S`, counted with the HTTP connections of its client address."""

    connections_per_client: ClientConnections = ClientConnections(64)

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._real_transport = transport
        super().connection_made(ClosingTransport(transport, self.loop, CLOSE_GRACE_S))  # type: ignore[arg-type]

    def connection_lost(self, exc: Exception | None) -> None:
        if isinstance(self.transport, ClosingTransport):
            self.transport.lost()
        if self.client:
            self.connections_per_client.release(self.client[0], self._real_transport)
        super().connection_lost(exc)


def protocols(settings: Any) -> tuple[type[BoundedHttpProtocol], type[BoundedWebSocketProtocol]]:
    """The HTTP and WebSocket protocol classes for uvicorn's `http=` and `ws=`, with the settings'
    limits."""
    counted = ClientConnections(settings.max_connections_per_client)
    http = type(
        "TiltlabHttpProtocol",
        (BoundedHttpProtocol,),
        {
            "max_head_bytes": settings.max_header_bytes,
            "max_head_lines": settings.max_headers + 1,
            "head_timeout_s": settings.header_timeout_s,
            "connections_per_client": counted,
        },
    )
    ws = type(
        "TiltlabWebSocketProtocol", (BoundedWebSocketProtocol,), {"connections_per_client": counted}
    )
    return http, ws
