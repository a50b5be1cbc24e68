"""The OpenAPI document describes the service that answers: every 2xx body typed, every error a
problem (one schema, application/problem+json), a bearer security scheme on the routes that need a
token, and the routers take what they need as declared dependencies."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

from service.api.app import create_app
from service.config import Settings

ROUTERS = Path(__file__).resolve().parents[2] / "service" / "api" / "routers"
OPEN = {("get", "/health"), ("get", "/ready")}  # no token needed
NON_JSON = {"application/xml", "text/html", "text/csv"}


@pytest.fixture(scope="module")
def document(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return create_app(Settings(data_dir=tmp_path_factory.mktemp("data"))).openapi()


def _operations(doc: dict[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    return [(method, path, op) for path, ops in doc["paths"].items() for method, op in ops.items()]


def _typed(schema: dict[str, Any], doc: dict[str, Any]) -> bool:
    """A schema that says what the body holds: a named model with properties, or a typed value."""
    ref = schema.get("$ref")
    if ref:
        target = doc["components"]["schemas"][ref.rsplit("/", 1)[1]]
        return bool(target.get("properties"))
    return schema.get("type") not in (None, "object") or bool(schema.get("properties"))


def test_every_2xx_response_is_typed(document: dict[str, Any]) -> None:
    untyped = []
    for method, path, op in _operations(document):
        for status, answer in op["responses"].items():
            if not status.startswith("2"):
                continue
            content = answer.get("content", {})
            if not content or not all(
                _typed(c.get("schema", {}), document) for c in content.values()
            ):
                untyped.append(f"{method.upper()} {path} {status}")
    assert untyped == []


def test_non_json_bodies_have_their_media_types(document: dict[str, Any]) -> None:
    paths = document["paths"]
    assert list(
        paths["/records/{record_id}/certificate"]["get"]["responses"]["200"]["content"]
    ) == ["application/xml"]
    assert list(
        paths["/records/{record_id}/certificate.html"]["get"]["responses"]["200"]["content"]
    ) == ["text/html"]
    assert list(paths["/records/{record_id}/points"]["get"]["responses"]["200"]["content"]) == [
        "text/csv"
    ]


def test_idempotent_repeats_are_declared(document: dict[str, Any]) -> None:
    assert {"200", "202"} <= set(document["paths"]["/calibrations"]["post"]["responses"])
    assert {"200", "201"} <= set(document["paths"]["/orders"]["post"]["responses"])


def test_every_error_is_the_one_problem_model(document: dict[str, Any]) -> None:
    schemas = document["components"]["schemas"]
    assert "HTTPValidationError" not in schemas and "ValidationError" not in schemas
    assert {"type", "title", "status", "detail", "instance"} <= set(
        schemas["Problem"]["properties"]
    )
    for method, path, op in _operations(document):
        errors = {s: a for s, a in op["responses"].items() if s[0] in "45"}
        if (method, path) not in OPEN:
            assert {"401", "403"} <= set(errors), f"{method} {path}"
        if op.get("parameters") or op.get("requestBody"):
            assert "422" in errors, f"{method} {path}"
        if op.get("requestBody"):
            assert "413" in errors, f"{method} {path}"
        for status, answer in errors.items():
            if (method, path) == ("get", "/ready"):
                continue  # 503 there is the readiness body, with its reasons
            assert answer["content"] == {
                "application/problem+json": {"schema": {"$ref": "#/components/schemas/Problem"}}
            }, f"{method} {path} {status}"


def test_bearer_security_scheme_on_every_route_but_health(document: dict[str, Any]) -> None:
    scheme = document["components"]["securitySchemes"]["bearerAuth"]
    assert (scheme["type"], scheme["scheme"]) == ("http", "bearer")
    for method, path, op in _operations(document):
        expected = [] if (method, path) in OPEN else [{"bearerAuth": []}]
        assert op.get("security", []) == expected, f"{method} {path}"


def test_routers_take_their_dependencies_declared() -> None:
    """No router reaches into the application's state: settings, store, benches and job manager come
    through service.api.deps, and unknown entities are mapped to 404 in one place."""
    for path in ROUTERS.glob("*.py"):
        text = path.read_text()
        assert "app.state" not in text, path.name
        assert not re.search(
            r"except UnknownEntity\b[^\n]*:\s*\n\s*raise ProblemError\(404", text
        ), path.name
