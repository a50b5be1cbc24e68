"""Content-Security-Policy on every HTML page the daemon serves, so that text someone stored (a
customer's name in a certificate, a note in a diagnosis report) can never run as script in a
colleague's browser.

* The dashboard (`/`): scripts, styles, images and connections from the daemon itself only: its own
  script files (no inline script), `fetch` and the WebSocket streams to the same host; style
  attributes allowed (layout only).
* The API's own pages (`/docs`, `/redoc`): the same, plus the one inline script each page starts its
  viewer with, allowed by its SHA-256 (worked out from the page as served), and the web worker
  ReDoc makes.
* Every other page (a certificate's printable page, a diagnosis report): a document, nothing runs
  at all; its own inline styles and the figures inlined as `data:` images.

Every answer also carries `X-Content-Type-Options: nosniff` (a download is never run as what it is
not).
"""

from __future__ import annotations

import base64
import hashlib
import re

from starlette.types import ASGIApp, Message, Receive, Scope, Send

_COMMON = "object-src 'none'; base-uri 'none'; frame-ancestors 'none'"
DASHBOARD = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' "
    f"data: blob:; connect-src 'self'; font-src 'self'; form-action 'self'; {_COMMON}"
)
API_PAGES = (
    "default-src 'self'; script-src 'self' {hashes}; style-src 'self' 'unsafe-inline'; img-src "
    "'self' data:;"
    f" connect-src 'self'; font-src 'self'; worker-src 'self' blob:; form-action 'self'; {_COMMON}"
)
DOCUMENT = (
    f"default-src 'none'; style-src 'unsafe-inline'; img-src data:; form-action 'none'; {_COMMON}"
)
_INLINE_SCRIPT = re.compile(rb"<script>(.*?)</script>", re.S)
_API_PAGES = frozenset({"/docs", "/redoc", "/docs/oauth2-redirect"})


def policy_of(path: str, body: bytes = b"") -> str:
    if path == "/":
        return DASHBOARD
    if path in _API_PAGES:
        hashes = " ".join(
            f"'sha256-{base64.b64encode(hashlib.sha256(script).digest()).decode()}'"
            for script in _INLINE_SCRIPT.findall(body)
        )
        return API_PAGES.format(hashes=hashes).replace("  ", " ")
    return DOCUMENT


def _with_nosniff(message: Message) -> list[tuple[bytes, bytes]]:
    """An answer's headers with nosniff, once, whatever the application said of it."""
    headers = [
        (name, value)
        for name, value in message.get("headers", [])
        if name.lower() != b"x-content-type-options"
    ]
    headers.append((b"x-content-type-options", b"nosniff"))
    return headers


def _is_html(headers: list[tuple[bytes, bytes]]) -> bool:
    """Whether the answer is an HTML page, which gets a Content-Security-Policy."""
    return any(
        name.lower() == b"content-type" and value.lower().startswith(b"text/html")
        for name, value in headers
    )


class ContentSecurity:
    """Adds the page's Content-Security-Policy to every text/html answer, and nosniff to every
    answer."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = scope.get("path", "")
        held: list[Message] = []  # an API page's start and body, until its inline scripts are known

        async def secured(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = _with_nosniff(message)
                message = {**message, "headers": headers}
                html = _is_html(headers)
                if html and path in _API_PAGES:
                    held.append(message)
                    return
                if html:
                    message["headers"] = [
                        *headers,
                        (b"content-security-policy", policy_of(path).encode()),
                    ]
            elif held:
                held.append(message)
                if message.get("more_body", False):
                    return
                start, *bodies = held
                held.clear()
                body = b"".join(m.get("body", b"") for m in bodies)
                start["headers"] = [
                    *start["headers"],
                    (b"content-security-policy", policy_of(path, body).encode()),
                ]
                await send(start)
                message = {"type": "http.response.body", "body": body}
            await send(message)

        await self.app(scope, receive, secured)
