"""HTTP spoken by hand on a socket, for requests no client library would send: a body sent while
the daemon may already have answered, and the problem document of an answer."""

from __future__ import annotations

import json
import select
import socket

from tests.helpers.waiting import eventually

MIB = 1 << 20


def response_while_sending(
    port: int, head: bytes, chunk: bytes, limit_bytes: int
) -> tuple[bytes, int]:
    """Send `head`, then `chunk` after `chunk` until the daemon answers; (its answer, body bytes
    sent).

    The sender's own buffer is kept small, so what it has sent is close to what the daemon took
    (left to autotuning, the kernels on both sides would swallow megabytes nobody read)."""
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 65536)
        sock.settimeout(30)
        sock.connect(("127.0.0.1", port))
        sock.sendall(head)
        sock.setblocking(False)
        sent = 0
        pending = b""
        answer = b""

        def step() -> tuple[bytes, int] | None:
            """One wait on the socket: what came in read, or the next piece sent; the answer and the
            bytes sent once the daemon has answered in full (or closed)."""
            nonlocal sent, pending, answer
            readable, writable, _ = select.select(
                [sock], [sock] if sent < limit_bytes else [], [], 0.5
            )
            if readable:
                try:
                    data = sock.recv(65536)
                except ConnectionResetError:
                    data = b""
                answer += data
                if (
                    not data
                    or b"\r\n\r\n" in answer
                    and len(answer.split(b"\r\n\r\n", 1)[1]) >= _length(answer)
                ):
                    return answer, sent
            elif writable:
                pending = pending or chunk  # a chunk goes whole, however many sends it takes
                try:
                    n = sock.send(pending)
                except (BlockingIOError, BrokenPipeError, ConnectionResetError):
                    return None
                sent, pending = sent + n, pending[n:]
            return None

        return eventually(
            step,
            timeout_s=60,
            every_s=0,
            what=lambda: f"an answer (none after {sent} bytes: {answer[:300]!r})",
        )


def _length(answer: bytes) -> int:
    head = answer.split(b"\r\n\r\n", 1)[0].decode("latin-1").lower()
    for line in head.split("\r\n"):
        if line.startswith("content-length:"):
            return int(line.split(":", 1)[1])
    return 1 << 62


def parse_problem(answer: bytes) -> tuple[int, dict[str, str], dict]:
    """An answer's status, headers (names in lower case) and problem document (JSON)."""
    head, body = answer.split(b"\r\n\r\n", 1)
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, v in (x.split(":", 1) for x in lines[1:])}
    return int(lines[0].split()[1]), headers, json.loads(body[: int(headers["content-length"])])
