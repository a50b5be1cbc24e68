"""The OpenAPI document as clients generate code from it: every error a problem (application/problem+json,
one `Problem` schema, FastAPI's own validation-error schema replaced since the body never has that shape)."""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from service.api.models.problem import PROBLEM_MEDIA_TYPE, PROBLEM_SCHEMA_REF, Problem, problem_responses

_FASTAPI_VALIDATION = ("HTTPValidationError", "ValidationError")


def document(app: FastAPI) -> dict[str, Any]:
    """The document of the application's routes, with the problem model in place of FastAPI's 422 body."""
    doc = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes,
                      tags=app.openapi_tags, servers=app.servers)
    schemas = doc.setdefault("components", {}).setdefault("schemas", {})
    problem = Problem.model_json_schema(ref_template="#/components/schemas/{model}")
    schemas.update(problem.pop("$defs", {}))
    schemas["Problem"] = problem
    validation = problem_responses(422)[422]
    for path in doc.get("paths", {}).values():
        for operation in path.values():
            responses = operation.get("responses", {})
            content = responses.get("422", {}).get("content", {})
            if "application/json" in content and "HTTPValidationError" in str(content["application/json"]):
                responses["422"] = dict(validation)
            for status, answer in responses.items():
                if status[0] in "45" and PROBLEM_MEDIA_TYPE not in answer.get("content", {}) and status != "503":
                    answer["content"] = {PROBLEM_MEDIA_TYPE: {"schema": PROBLEM_SCHEMA_REF}}
    if not any(name in str(doc["paths"]) for name in _FASTAPI_VALIDATION):
        for name in _FASTAPI_VALIDATION:
            schemas.pop(name, None)
    return doc


def install(app: FastAPI) -> None:
    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = document(app)
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]  # FastAPI's documented way to supply the schema
