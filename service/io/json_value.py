"""JSON of any shape, for the places that handle a document they do not define: the OpenAPI
document FastAPI and pydantic generate, what `discrepancy.report.clean` makes of a report, a job's
API body passed through to its live stream. Where the shape is known, a TypedDict names it instead.

The lowest layer both the API and the discrepancy workflow import (nothing here runs)."""

from __future__ import annotations

JSONValue = str | int | float | bool | None | list["JSONValue"] | dict[str, "JSONValue"]
JSONObject = dict[str, JSONValue]


def members(value: JSONValue) -> JSONObject:
    """The members of a JSON object, the same dict (changes to it are changes to the document); none
    where the value is not an object."""
    return value if isinstance(value, dict) else {}


def items(value: JSONValue) -> list[JSONValue]:
    """The items of a JSON array, the same list; none where the value is not an array."""
    return value if isinstance(value, list) else []
