"""HTTP details on every route, including routes added later: HEAD wherever GET is served (same
status and headers, no body), and every 405 answer carries `Allow` with all the path's methods."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.config import Settings

UNSCHEMATISED_GETS = ("/", "/docs", "/redoc", "/openapi.json", "/docs-assets/swagger-ui.css")
METHODS = ("GET", "POST", "PUT", "PATCH", "DELETE")


@pytest.fixture
def client(tmp_path):  # type: ignore[no-untyped-def]
    with TestClient(create_app(Settings(data_dir=tmp_path)), raise_server_exceptions=False) as c:
        yield c


def _schema_paths(client: TestClient) -> dict[str, set[str]]:
    paths = client.get("/openapi.json").json()["paths"]
    return {
        re.sub(r"\{[^}]+\}", "1", p): {m.upper() for m in ops if m.upper() in METHODS}
        for p, ops in paths.items()
    }


def _streams(client: TestClient, path: str) -> bool:
    for template, ops in client.get("/openapi.json").json()["paths"].items():
        if re.sub(r"\{[^}]+\}", "1", template) == path:
            content = ops.get("get", {}).get("responses", {}).get("200", {}).get("content", {})
            return "text/event-stream" in content
    return False


def test_head_answers_every_get_route(client: TestClient) -> None:
    gets = [p for p, ms in _schema_paths(client).items() if "GET" in ms] + list(UNSCHEMATISED_GETS)
    assert "/health" in gets
    for path in gets:
        head = client.head(path)
        assert head.status_code != 405, path
        assert head.content == b"", path
        if _streams(client, path):
            continue  # a stream's GET never ends; its HEAD did, with the stream's headers
        get = client.get(path)
        assert head.status_code == get.status_code, path
        assert head.headers.get("content-type") == get.headers.get("content-type"), path
        # the length a GET would have had (readings vary in length)
        if "content-length" in get.headers:
            assert int(head.headers["content-length"]) > 0, path


def test_405_carries_allow_with_every_method_of_the_path(client: TestClient, tmp_path) -> None:  # type: ignore[no-untyped-def]
    paths = {**_schema_paths(client), "/docs": {"GET"}, "/": {"GET"}}
    # with a token: without one, a protected path answers 401 whatever the method (the token comes
    # first)
    admin = {"Authorization": "Bearer " + (tmp_path / "admin.token").read_text().strip()}
    for path, served in paths.items():
        refused = next(m for m in ("DELETE", "PATCH", "PUT", "POST") if m not in served)
        r = client.request(refused, path, headers=admin)
        assert r.status_code == 405, (refused, path)
        assert r.headers["content-type"].startswith("application/problem+json")
        allow = {m.strip() for m in r.headers["allow"].split(",")}
        expected = served | ({"HEAD"} if "GET" in served else set())
        assert allow == expected, (path, allow, expected)


def test_allow_lists_methods_of_separate_routes_on_one_path(tmp_path) -> None:  # type: ignore[no-untyped-def]
    app = create_app(Settings(data_dir=tmp_path))

    @app.get("/lab-notes")
    def read_notes() -> list[str]:
        return []

    @app.post("/lab-notes")
    def add_note() -> dict[str, str]:
        return {}

    with TestClient(app) as c:
        admin = {"Authorization": "Bearer " + (tmp_path / "admin.token").read_text().strip()}
        r = c.delete("/lab-notes", headers=admin)
        assert r.status_code == 405
        assert r.headers["allow"] == "GET, HEAD, POST"
        assert c.head("/lab-notes", headers=admin).status_code == 200
