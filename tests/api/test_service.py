"""The service as people start it: schema upgraded at start-up, health, tilt, problem+json."""

import os
import subprocess
import sys

import httpx
import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.config import Settings
from tests.helpers.running_service import free_port, running_service


@pytest.fixture
def client(tmp_path):
    app = create_app(Settings(data_dir=tmp_path))
    with TestClient(app) as c:
        yield c


def test_health_reports_schema_at_head_and_the_bench(client):
    r = client.get("/health")
    assert r.status_code == 200
    body = r.json()
    assert body["status"] == "ok" and body["schema_revision"] and body["bench"] == "sim-stage"
    assert body["database"].startswith("sqlite")


def test_tilt_serves_readings_and_says_when_uncorrected(client, tmp_path):
    assert client.get("/tilt").status_code == 401
    token = (tmp_path / "admin.token").read_text().strip()
    body = client.get("/tilt", headers={"Authorization": f"Bearer {token}"}).json()
    raw = body["raw"]
    # stage at zero, mounting errors < 1 deg
    assert (
        abs(raw["measurement_sensor"]["x_deg"]) < 1.0
        and abs(raw["reference_sensor"]["y_deg"]) < 1.0
    )
    assert body["table_tilt"] is None and "no active calibration" in body["note"]


def test_unknown_route_is_problem_json(client, tmp_path):
    token = (tmp_path / "admin.token").read_text().strip()
    r = client.get("/nope", headers={"Authorization": f"Bearer {token}"})
    assert r.status_code == 404 and r.headers["content-type"].startswith("application/problem+json")
    assert r.json()["status"] == 404
    r = client.get("/nope")  # a stranger learns no more than that a token is needed
    assert r.status_code == 401 and r.headers["content-type"].startswith("application/problem+json")


def test_bench_scenario_setting_chooses_the_simulated_bench(tmp_path):
    import json

    from service.scenarios.model import scenario_data

    data, _ = scenario_data("seed000")
    data["name"] = "my-bench"
    path = tmp_path / "my-bench.json"
    path.write_text(json.dumps(data))
    with TestClient(create_app(Settings(data_dir=tmp_path, bench_scenario=str(path)))) as c:
        token = (tmp_path / "admin.token").read_text().strip()
        benches = c.get("/benches", headers={"Authorization": f"Bearer {token}"}).json()["benches"]
        assert benches[0]["simulated"]["scenario"] == "my-bench"


def test_tiltlab_serve_starts_on_a_fresh_data_dir(tmp_path):
    """The README's first command, minus the install: the console entry point serves /health."""
    with running_service(tmp_path / "data") as base:
        r = httpx.get(f"{base}/health", timeout=5)
    assert r.status_code == 200 and r.json()["status"] == "ok"
    assert (tmp_path / "data" / "tiltlab.db").exists()


def test_dashboard_page_and_assets_are_served(client):
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert '<script type="module" src="/web/js/main.js">' in page.text
    for asset, kind in (
        ("/web/js/main.js", "javascript"),
        ("/web/js/views/live.js", "javascript"),
        ("/web/vendor/uplot/uPlot.esm.js", "javascript"),
        ("/web/dashboard.css", "text/css"),
        ("/favicon.ico", "image/svg+xml"),
    ):
        r = client.get(asset)
        assert r.status_code == 200 and kind in r.headers["content-type"]
    missing = client.get("/web/nope.js")
    assert missing.status_code == 404 and missing.headers["content-type"].startswith(
        "application/problem+json"
    )


@pytest.mark.parametrize(
    ("env", "match"),
    [
        ({"TILTLAB_BENCH_SCENARIO": "nope"}, "TILTLAB_BENCH_SCENARIO.*no such preset"),
        ({"TILTLAB_BENCH_SCENARIO": "seed002-b55"}, "TILTLAB_BENCH_SCENARIO.*needs a stage"),
        ({"TILTLAB_DATABASE_URL": "mysql://u@h/db"}, "only sqlite and postgresql"),
        (
            {"TILTLAB_SIM_SPEED": "50"},
            "TILTLAB_SIM_SPEED.*50 is more than the simulated stage bench can run.*at most 28",
        ),
    ],
)
def test_tiltlab_serve_refuses_unusable_settings_with_one_line(tmp_path, env, match):
    """Exit 2 and a message naming the setting, before serving; no start-up traceback."""
    import re

    env = {**os.environ, "TILTLAB_DATA_DIR": str(tmp_path / "data"), **env}
    proc = subprocess.run(
        [sys.executable, "-m", "service", "serve", "--port", str(free_port())],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and re.search(match, proc.stderr), proc.stderr


def test_unexpected_failure_is_problem_json_without_internals(tmp_path):
    from service.storage.engine import make_engine

    app = create_app(Settings(data_dir=tmp_path))
    with TestClient(app, raise_server_exceptions=False) as c:
        # a directory: the database cannot be opened
        app.state.engine = make_engine(f"sqlite:///{tmp_path}")
        r = c.get("/health")
    assert r.status_code == 500 and r.headers["content-type"].startswith("application/problem+json")
    body = r.json()
    assert (
        body["status"] == 500
        and body["instance"] == "/health"
        and "Traceback" not in body["detail"]
    )
