"""What an integrator generates from /openapi.json compiles what the README sends: TypeScript types
made by openapi-typescript (default settings) type-check every request body of the README's curl
session under `tsc --strict`. And the document's details a generator reads: a request field with a
default is optional, every 201 and 202 declares its Location header, the description names the
routes open without a token.

The tools are the pinned npm packages of package.json (`npm ci`, run by .ci/run); without them the
compile test is skipped, saying so, and the document checks still run."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path
from typing import Any

import pytest

from service.api.app import create_app
from service.config import Settings

ROOT = Path(__file__).resolve().parents[2]
BIN = ROOT / "node_modules" / ".bin"
needs_tools = pytest.mark.skipif(
    not (BIN / "tsc").exists() or not (BIN / "openapi-typescript").exists(),
    reason="needs the npm tools of package.json (npm ci; .ci/run installs them)",
)


@pytest.fixture(scope="module")
def document(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return create_app(Settings(data_dir=tmp_path_factory.mktemp("data"))).openapi()


def readme_bodies() -> list[tuple[str, str, dict[str, Any]]]:
    """(method, route, body) of every curl command of the README that sends JSON."""
    text = (ROOT / "README.md").read_text()
    found = []
    for command, route in re.findall(r"curl\b(.*?)\$BASE(/[^\s#]*)", text, flags=re.S):
        body = re.search(r"-d '([^']*)'", command)
        if body:
            found.append(("post", route, json.loads(body.group(1))))
    return found


def schema_path(document: dict[str, Any], route: str) -> str:
    """The document's path template that matches a concrete route (/records/1/diagnose ->
    /records/{record_id}/diagnose)."""
    for template in document["paths"]:
        if re.fullmatch(re.sub(r"\{[^}]+\}", "[^/]+", template), route):
            return template
    raise AssertionError(f"{route} is not in the OpenAPI document")


def test_the_readme_sends_bodies():
    routes = [route for _, route, _ in readme_bodies()]
    assert "/calibrations" in routes and "/stage/level" in routes, routes


def test_a_request_field_with_a_default_is_optional(document):
    schemas = document["components"]["schemas"]
    request = schemas["CalibrationRequest"]
    assert "samples_per_point" not in request.get("required", [])
    assert "default 10" in request["properties"]["samples_per_point"]["description"]
    for name in ("CalibrationRequest", "Grid", "Settle", "Validation", "Level", "DiagnoseRequest"):
        for field, prop in schemas[name].get("properties", {}).items():
            assert "default" not in prop or field in schemas[name].get("required", []), (
                name,
                field,
            )


def test_every_201_and_202_declares_its_location(document):
    declared = []
    for path, operations in document["paths"].items():
        for method, operation in operations.items():
            for status in ("201", "202"):
                if status in operation["responses"]:
                    assert "Location" in operation["responses"][status].get("headers", {}), (
                        method,
                        path,
                        status,
                    )
                    declared.append((method, path))
    for wanted in (
        "/calibrations",
        "/records/{record_id}/diagnose",
        "/diagnoses/{diagnosis_id}/adopt",
        "/orders",
    ):
        assert ("post", wanted) in declared, wanted


def test_the_description_names_every_open_route(document):
    description = document["info"]["description"]
    assert "/health" in description and "/ready" in description


def generate_types(document: dict[str, Any], folder: Path) -> Path:
    """openapi-typescript's types of the document (default settings), written to folder/api.ts."""
    spec = folder / "openapi.json"
    spec.write_text(json.dumps(document))
    made = subprocess.run(
        [str(BIN / "openapi-typescript"), str(spec), "-o", str(folder / "api.ts")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert made.returncode == 0, made.stdout + made.stderr
    return folder / "api.ts"


@needs_tools
def test_generated_typescript_types_compile_the_readme_bodies(document, tmp_path):
    generate_types(document, tmp_path)
    lines = ['import type { paths } from "./api";']
    for i, (method, route, body) in enumerate(readme_bodies()):
        template = schema_path(document, route)
        lines.append(
            f'const body{i}: paths["{template}"]["{method}"]["requestBody"] = '
            f'{{ content: {{ "application/json": {json.dumps(body)} }} }};'
        )
        lines.append(f"void body{i};")
    (tmp_path / "readme.ts").write_text("\n".join(lines) + "\n")
    checked = subprocess.run(
        [
            str(BIN / "tsc"),
            "--noEmit",
            "--strict",
            "--target",
            "es2022",
            "--module",
            "es2022",
            "--moduleResolution",
            "bundler",
            str(tmp_path / "readme.ts"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert checked.returncode == 0, (
        checked.stdout + checked.stderr + (tmp_path / "readme.ts").read_text()
    )


NEW_NAMES = (
    "standard_uncertainty_x_deg",
    "standard_uncertainty_y_deg",
    "expanded_uncertainty_x_deg",
    "expanded_uncertainty_y_deg",
    "coverage_factor_x",
    "coverage_factor_y",
    "coverage_probability",
    "degrees_of_freedom_x",
    "degrees_of_freedom_y",
)
FORMER_NAMES = ("u_x_deg", "u_y_deg", "k", "k_y")


@needs_tools
def test_generated_types_carry_the_new_names_and_mark_the_former_ones_deprecated(
    document, tmp_path
):
    """An integrator's generated client sees `/tilt`'s table tilt under both names, and the former
    ones (the expanded uncertainties and their factors) flagged `@deprecated` in its editor."""
    text = generate_types(document, tmp_path).read_text()
    table = re.search(r"\n        TableTilt: \{\n(.*?)\n        \};", text, flags=re.S)
    assert table is not None, "no TableTilt type in the generated types"
    # each property with the JSDoc block just above it
    fields = dict(
        (name, doc)
        for doc, name in re.findall(r"/\*\*(.*?)\*/\s*\n\s*(\w+)\??:", table.group(1), flags=re.S)
    )
    for name in NEW_NAMES:
        assert name in fields and "@deprecated" not in fields[name], name
    for name in FORMER_NAMES:
        assert name in fields and "@deprecated" in fields[name], name
    assert "EXPANDED" in fields["u_x_deg"] and "EXPANDED" in fields["u_y_deg"]
