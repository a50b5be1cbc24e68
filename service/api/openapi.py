"""The OpenAPI document as clients generate code from it: every error a problem
(application/problem+json, one `Problem` schema, FastAPI's own validation-error schema replaced
since the body never has that shape), the `Location` header of every 201 and 202 declared, and a
request field with a default optional in the code generated from it."""

from __future__ import annotations

import json
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from service.api.models.problem import (
    PROBLEM_MEDIA_TYPE,
    PROBLEM_SCHEMA_REF,
    Problem,
    problem_responses,
)
from service.io.json_value import JSONObject, JSONValue, items, members

_FASTAPI_VALIDATION = ("HTTPValidationError", "ValidationError")
# Every 201 and 202 of the API says where what it made (or started) is read.
LOCATION_HEADER: JSONObject = {
    "Location": {
        "description": "the address of what was made or started, e.g. /calibrations/7",
        "schema": {"type": "string"},
    }
}


def document(app: FastAPI) -> JSONObject:
    """The document of the application's routes, with the problem model in place of FastAPI's 422
    body."""
    doc: JSONObject = get_openapi(
        title=app.title,
        version=app.version,
        description=app.description,
        routes=app.routes,
        tags=app.openapi_tags,
        servers=app.servers,
    )
    schemas = members(members(doc.setdefault("components", {})).setdefault("schemas", {}))
    problem = Problem.model_json_schema(ref_template="#/components/schemas/{model}")
    schemas.update(problem.pop("$defs", {}))
    schemas["Problem"] = problem
    _errors_as_problems(doc)
    _location_headers(doc)
    _defaults_in_words(schemas, _request_only_schemas(doc))
    if not any(name in str(doc["paths"]) for name in _FASTAPI_VALIDATION):
        for name in _FASTAPI_VALIDATION:
            schemas.pop(name, None)
    _state_travel(app, schemas)
    _state_procedures(app, schemas)
    _json_schema_bounds(doc)
    return doc


def _errors_as_problems(doc: JSONObject) -> None:
    """Every error answer of every operation declared a problem: FastAPI's 422 body replaced, the
    other 4xx and 5xx given the problem schema (503 keeps what its route declares)."""
    validation = problem_responses(422)[422]
    for path in members(doc.get("paths", {})).values():
        for operation in members(path).values():
            responses = members(members(operation).get("responses", {}))
            content = members(members(responses.get("422", {})).get("content", {}))
            if "application/json" in content and "HTTPValidationError" in str(
                content["application/json"]
            ):
                responses["422"] = dict(validation)
            for status, answer in responses.items():
                if (
                    status[0] in "45"
                    and PROBLEM_MEDIA_TYPE not in members(members(answer).get("content", {}))
                    and status != "503"
                ):
                    members(answer)["content"] = {
                        PROBLEM_MEDIA_TYPE: {"schema": PROBLEM_SCHEMA_REF}
                    }


def _location_headers(doc: JSONObject) -> None:
    """The `Location` header declared on every 201 and 202 answer."""
    for path in members(doc.get("paths", {})).values():
        for operation in members(path).values():
            for status in ("201", "202"):
                responses = members(members(operation).get("responses", {}))
                if status in responses:
                    headers = members(members(responses[status]).setdefault("headers", {}))
                    headers.update(LOCATION_HEADER)


def _runnable(benches: list[Any]) -> list[str]:
    """The procedures some bench of this daemon runs: one of its kind, whose instruments it has."""
    from service.jobs.registry import PROCEDURES

    return [
        name
        for name, procedure in PROCEDURES.items()
        if any(
            bench.kind == getattr(procedure, "bench_kind", "stage")
            and all(role in bench.devices for role in getattr(procedure, "read_roles", ()))
            for bench in benches
        )
    ]


def _state_procedures(app: FastAPI, schemas: JSONObject) -> None:
    """`POST /calibrations` procedures: those a bench of this daemon runs (its kind and
    instruments)."""
    benches = list((getattr(app.state, "benches", None) or {}).values())
    request = schemas.get("CalibrationRequest")
    if not benches or request is None:
        return
    runnable = _runnable(benches)
    request = members(request)
    prop = members(members(request.get("properties", {})).get("procedure", {}))
    if "enum" in prop:
        prop["enum"] = [name for name in items(prop["enum"]) if name in runnable]
        prop["description"] = (
            "a procedure a bench of this daemon runs (its kind and instruments): "
            + ", ".join(runnable)
        )
    if "allOf" in request:
        request["allOf"] = [
            case for case in items(request["allOf"]) if _procedure_of(case) in runnable
        ]


def _procedure_of(case: JSONValue) -> JSONValue:
    """The procedure a case of `CalibrationRequest`'s allOf is for (its `if`'s constant)."""
    condition = members(members(case)["if"])
    return members(members(condition["properties"])["procedure"])["const"]


_BOUNDS = {"ge": "minimum", "le": "maximum", "gt": "exclusiveMinimum", "lt": "exclusiveMaximum"}


def _json_schema_bounds(node: JSONValue) -> None:
    """Bounds of the counts (whole numbers that may be written 18.0) as JSON Schema words: pydantic
    leaves a bound it cannot place inside a validator under its own name (`ge`, `le`), which no
    client reads."""
    if isinstance(node, dict):
        if node.get("type") in ("integer", "number"):
            for ours, theirs in _BOUNDS.items():
                if ours in node:
                    node.setdefault(theirs, node.pop(ours))
        for value in node.values():
            _json_schema_bounds(value)
    elif isinstance(node, list):
        for value in node:
            _json_schema_bounds(value)


def _state_travel(app: FastAPI, schemas: JSONObject) -> None:
    """`POST /stage/move` angles within the stage travel of the daemon's stage benches (the widest,
    where they differ: the route checks each bench's own)."""
    benches = getattr(app.state, "benches", None) or {}
    travels = [
        bench.config.stage_bench().travel_deg
        for bench in benches.values()
        if getattr(bench, "kind", None) == "stage"
    ]
    move = members(members(schemas.get("Move", {})).get("properties", {}))
    if travels:
        for axis in ("x_deg", "y_deg"):
            if axis in move:
                members(move[axis]).update(
                    minimum=-max(travels),
                    maximum=max(travels),
                    description=f"raw stage angle, within the stage's travel (±{max(travels):g} "
                    "deg)",
                )


def install(app: FastAPI) -> None:
    def openapi() -> JSONObject:
        if app.openapi_schema is None:
            app.openapi_schema = document(app)
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]  # FastAPI's documented way to supply the schema


def _refs(node: JSONValue) -> set[str]:
    """The component schemas a part of the document names."""
    if isinstance(node, dict):
        found = {str(node["$ref"]).rsplit("/", 1)[1]} if "$ref" in node else set()
        return found.union(*(_refs(value) for key, value in node.items() if key != "$ref"))
    if isinstance(node, list):
        return set().union(*(_refs(value) for value in node))
    return set()


def _closure(names: set[str], schemas: JSONObject) -> set[str]:
    seen: set[str] = set()
    todo = list(names)
    while todo:
        name = todo.pop()
        if name in seen or name not in schemas:
            continue
        seen.add(name)
        todo += _refs(schemas[name])
    return seen


def _request_only_schemas(doc: JSONObject) -> set[str]:
    """Component schemas only request bodies use (what a client sends, never what it reads back)."""
    schemas = members(members(doc["components"])["schemas"])
    sent: set[str] = set()
    read: set[str] = set()
    for path in members(doc.get("paths", {})).values():
        for operation in members(path).values():
            sent |= _refs(members(operation).get("requestBody", {}))
            read |= _refs(members(operation).get("responses", {}))
    return _closure(sent, schemas) - _closure(read, schemas)


def _defaults_in_words(schemas: JSONObject, names: set[str]) -> None:
    """A request field with a default may be left out: it is not `required`, and its default is said
    in its description rather than as the `default` keyword, which common TypeScript generators
    (openapi-typescript's default settings) turn into a field the client must send."""
    for name in names:
        for member in members(members(schemas[name]).get("properties", {})).values():
            prop = members(member)
            if "default" not in prop:
                continue
            default = prop.pop("default")
            if default is None:
                continue  # null is what leaving it out means
            said = f"default {json.dumps(default)} when left out"
            prop["description"] = (
                f"{prop['description']}; {said}" if prop.get("description") else said
            )
