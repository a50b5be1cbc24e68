"""No token in any log line: tokens are blanked in every log record as it is made.

The ASGI server's access log and WebSocket lines print the request path with its query, where a
WebSocket client may carry `?token=...`. Blanking happens in the process's log-record factory, so
it covers every logger (the server's, ours, libraries') and every format, including the access
log's formatter, which reads the record's arguments rather than its message.
"""

from __future__ import annotations

import logging
import re
from typing import Any

# `token=<value>` in a query string or fragment; `bearer.<token>` subprotocols; a token's own text.
_PATTERNS = (
    (re.compile(r"(token=)[^&\s\"'#]+", re.IGNORECASE), r"\1[redacted]"),
    (re.compile(r"(bearer[. ])[A-Za-z0-9._~+/=-]{8,}", re.IGNORECASE), r"\1[redacted]"),
    (re.compile(r"\btl_[A-Za-z0-9_-]{16,}"), "tl_[redacted]"),
)
REDACTED = "[redacted]"
# Text none of the patterns can match (nearly every log line) is given back after one search.
_SUSPECT = re.compile(r"token=|bearer[. ]|tl_", re.IGNORECASE)


def redact(text: str) -> str:
    if _SUSPECT.search(text) is None:
        return text
    for pattern, replacement in _PATTERNS:
        text = pattern.sub(replacement, text)
    return text


def _clean(value: Any) -> Any:
    return redact(value) if isinstance(value, str) else value


def install_log_redaction() -> None:
    """Blank tokens in every log record of this process from now on (idempotent)."""
    current = logging.getLogRecordFactory()
    if getattr(current, "redacts_tokens", False):
        return

    def factory(*args: Any, **kwargs: Any) -> logging.LogRecord:
        record = current(*args, **kwargs)
        record.msg = _clean(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(_clean(arg) for arg in record.args)
        elif isinstance(record.args, dict):
            record.args = {key: _clean(value) for key, value in record.args.items()}
        return record

    factory.redacts_tokens = True  # type: ignore[attr-defined]  # a mark on the function: installed once per process
    logging.setLogRecordFactory(factory)
