"""Schemathesis against the running daemon: every operation answers what its OpenAPI document says.

Examples from the document and generated requests (a few per operation, positive and negative) go to
a real `tiltlab serve` on its simulated bench; the checks are that no answer is a server error, every
answer's status is a documented one, and its content type and body match what is documented for it.
Webhook URLs the generator invents never leave the machine: the daemon's outgoing HTTP goes to a
closed loopback port. `DELETE /tokens/{name}` is left out: the generator learns token names from
`GET /tokens` and would revoke the very token it runs with (tests/daemon/test_tokens_routes.py
tests that route).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from tests.api.running_service import free_port, running_service

SCHEMATHESIS = shutil.which("schemathesis", path=str(Path(sys.executable).parent)) or shutil.which("schemathesis")
pytestmark = pytest.mark.skipif(SCHEMATHESIS is None, reason="schemathesis is part of the dev extra")

CHECKS = "not_a_server_error,response_schema_conformance,status_code_conformance,content_type_conformance"


def test_every_operation_answers_as_documented(tmp_path: Path) -> None:
    nowhere = f"http://127.0.0.1:{free_port()}"  # nothing listens there: deliveries fail, on this machine
    data = tmp_path / "data"
    env = {"TILTLAB_SIM_SPEED": "20", "HTTP_PROXY": nowhere, "HTTPS_PROXY": nowhere, "NO_PROXY": "",
           "TILTLAB_LAB_NAME": "Inclination Lab GmbH", "TILTLAB_LAB_CITY": "Braunschweig",
           "TILTLAB_LAB_COUNTRY_CODE": "DE"}
    with running_service(data, **env) as base:
        admin = {"Authorization": "Bearer " + (data / "admin.token").read_text().strip()}
        made = httpx.post(f"{base}/tokens", json={"name": "fuzzer", "scopes": ["admin"]}, headers=admin, timeout=30)
        assert made.status_code == 201, made.text
        r = subprocess.run([str(SCHEMATHESIS), "run", f"{base}/openapi.json",
                            "-H", f"Authorization: Bearer {made.json()['token']}", "--checks", CHECKS,
                            "--phases", "examples,fuzzing", "--max-examples", "5", "--workers", "1",
                            "--request-timeout", "60", "--generation-with-security-parameters", "false",
                            "--exclude-path-regex", "^/tokens/"],
                           capture_output=True, text=True, timeout=600, env={**os.environ, "NO_COLOR": "1"},
                           cwd=tmp_path)  # its cache of examples stays out of the repository
    report = r.stdout + r.stderr
    Path(os.environ.get("TILTLAB_SCHEMATHESIS_REPORT", tmp_path / "schemathesis.txt")).write_text(report)
    assert r.returncode == 0, report[-8000:]
    summary = report.split("SUMMARY")[-1]
    assert "passed" in summary and "unique failures" not in summary, summary
    assert "Authentication failed" not in report, report[-4000:]  # every operation was reached with the token
