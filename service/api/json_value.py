"""JSON of any shape, where the API handles a document it does not define: the OpenAPI document
FastAPI and pydantic generate, and the parts of it the routes declare."""

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
