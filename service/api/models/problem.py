"""The one error body of every route: RFC 9457 problem details, served as
application/problem+json."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from service.io.json_value import JSONObject

PROBLEM_MEDIA_TYPE = "application/problem+json"


class FieldError(BaseModel):
    loc: list[str] = Field(
        description="where the value sits: body, query or path, then the field's path"
    )
    msg: str


class Problem(BaseModel):
    """RFC 9457 problem details; `field`, `errors` and other members are extensions."""

    model_config = ConfigDict(extra="allow", title="Problem")
    type: str = Field("about:blank", description="a URI naming the kind of problem")
    title: str = Field(description="short summary of the kind of problem")
    status: int = Field(description="the HTTP status code")
    detail: str = Field(description="what was wrong with this request, in words")
    instance: str | None = Field(None, description="the path of the request")
    field: str | None = Field(None, description="the field or parameter at fault, where one was")
    errors: list[FieldError] | None = Field(
        None, description="422 for an invalid body or parameter: every value at fault"
    )


_WHEN = {
    401: "No valid token (`Authorization: Bearer <token>`)",
    403: "The token lacks the scope this route needs",
    404: "Unknown bench, job, record or other entity named in the request",
    409: "Conflicts with the current state (a bench held by a job, a decision already made, ...)",
    413: "The request body is larger than the daemon accepts",
    422: "A body or parameter that cannot be used; `field` names it",
    429: "Too many requests of a kind from this client (unknown tokens); `Retry-After` says when "
    "to try again",
    503: "The database did not answer in time, a device the request needs is not answering, or the "
    "laboratory is"
    " not configured; `Retry-After` says when to try again where waiting mends it",
    507: "The data directory's disk (or the database server's) is full: nothing was stored",
}
PROBLEM_SCHEMA_REF: JSONObject = {"$ref": "#/components/schemas/Problem"}


def problem_responses(*statuses: int) -> dict[int | str, JSONObject]:
    """The `responses=` of a route for the error statuses it can give, each a problem."""
    return {
        status: {
            "description": _WHEN[status],
            "content": {PROBLEM_MEDIA_TYPE: {"schema": PROBLEM_SCHEMA_REF}},
        }
        for status in statuses
    }


# What routes commonly give: a token check (unknown tokens slowed down, the database asked with a
# deadline), and on routes with a body the size limit and validation; a write may find the disk
# full.
READ = (401, 403, 422, 429, 503)
WRITE = (401, 403, 413, 422, 429, 503, 507)
