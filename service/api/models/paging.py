"""Lists a page at a time: every list route takes `cursor` (the `next_cursor` of the page before)
and `limit`, so what one request reads and sends is bounded however long the list grows."""

from __future__ import annotations

import re

from fastapi.responses import Response
from pydantic import BaseModel

DEFAULT_PAGE = 50
MAX_PAGE = 500
CURSOR = "`next_cursor` of the previous page (leave out for the first page)"
LIMIT = f"items per page (1 to {MAX_PAGE})"


def json_answer(body: BaseModel) -> Response:
    """A response model serialised where it was made (a request thread), not on the event loop: a
    page of records is hundreds of kB of JSON, and serialising it there would hold every other
    request up."""
    return Response(body.model_dump_json().encode(), media_type="application/json")


# RFC 3339 date-time with its zone: what a time in a query must be (`0.5` or a bare date are not
# times)
_RFC3339 = re.compile(r"\d{4}-\d{2}-\d{2}[Tt ]\d{2}:\d{2}:\d{2}(\.\d+)?([Zz]|[+-]\d{2}:\d{2})")


def rfc3339(value: object) -> object:
    """A query's time as given: refused unless it is RFC 3339 text with a zone (pydantic alone takes
    numbers as Unix times and times without a zone)."""
    if isinstance(value, str) and not _RFC3339.fullmatch(value):
        raise ValueError("not an RFC 3339 time with a zone (e.g. 2026-03-01T12:00:00Z)")
    return value
