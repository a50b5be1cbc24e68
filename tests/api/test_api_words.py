"""Errors in the API's own words: a broken JSON body and a levelling target out of reach."""

from __future__ import annotations

from fastapi.testclient import TestClient

from service.api.app import create_app
from service.config import Settings


def test_a_body_that_is_not_json_is_said_so(tmp_path) -> None:
    with TestClient(create_app(Settings(data_dir=tmp_path, sim_speed=20.0))) as client:
        h = {
            "Authorization": "Bearer " + (tmp_path / "admin.token").read_text().strip(),
            "Content-Type": "application/json",
        }
        r = client.post("/calibrations", headers=h, content=b'{"procedure": "stage-grid",,}')
        assert r.status_code == 422
        detail = r.json()["detail"]
        assert detail.startswith("body: not valid JSON at character "), detail
        assert "JSON decode error" not in detail and "body.2" not in detail


def test_a_body_that_is_not_utf8_text_is_a_422_naming_the_body(tmp_path) -> None:
    with TestClient(create_app(Settings(data_dir=tmp_path, sim_speed=20.0))) as client:
        h = {
            "Authorization": "Bearer " + (tmp_path / "admin.token").read_text().strip(),
            "Content-Type": "application/json",
        }
        r = client.post("/stage/stop", headers=h, content=b'{"bench": "\xc3\x28"}')
    assert r.status_code == 422, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    assert r.json()["field"] == "body" and "UTF-8" in r.json()["detail"]
