"""Schemathesis against the running daemon: every operation answers what its OpenAPI document says,
with every check this Schemathesis version offers (`--checks all`; its time limit on answers is
the request timeout: a tighter one would be a wall-clock assertion, which no test makes), in its
examples, coverage, fuzzing and stateful phases.

Examples from the document, the coverage phase's boundary values, generated requests (positive and
negative) go to a real `tiltlab serve` on its simulated bench. Among the checks: no answer is a
server error, every status, content type, header and body is the documented one, schema-valid data
is accepted (`positive_data_acceptance`) and invalid data refused (`negative_data_rejection`), a
request without the token is refused (`ignored_auth`), unsupported methods are 405 with `Allow`.

What is left out, and why:

* `DELETE /tokens/{name}` (alone: `PATCH /tokens/{name}` is fuzzed): the generator learns token
  names from `GET /tokens` and would revoke the very token it runs with
  (tests/daemon/test_tokens_routes.py tests that route, the last admin token's refusal included).
  For the same reason `PATCH /tokens/{name}` is fuzzed on a token of its own (`PATCHED_TOKEN`):
  its bodies change a token's person, and the fuzzer's token must keep the person with a function
  that approving and rejecting a record ask of their signer (without one both are 403 whatever
  the record, and the run would not reach them).
* `positive_data_acceptance` also takes 422 on five operations, where a schema-valid request can be
  refused for what JSON Schema cannot state: `POST /calibrations` (the grid must lie within the
  bench's travel and hold as many points as the method needs, a product of two counts; the standards
  and order it names must exist and be valid: the lab's stored data), `POST /standards` (`due_on`
  must come after `calibrated_on`: two values compared), `POST /orders` (an `Idempotency-Key` used
  before for another body is 422, as the IETF draft on that header asks: the lab's stored data),
  `GET /feed` (a cursor must be one the feed gave out: it is opaque) and `POST /stage/level` (a
  table tilt is reached only where stage angles within the travel give it through the active
  record's model: the lab's stored data). Everything else the routes enforce the document states
  (docs/api.md, "The OpenAPI document and request validation").
* `POST /records/{record_id}/diagnose` may answer 503 "Diagnoses busy" (with `Retry-After`) once
  `TILTLAB_MAX_DIAGNOSES` diagnoses are queued or running: the fuzzer asks for them faster than they
  finish, and the document states that answer.

A longer run: `TILTLAB_SCHEMATHESIS_MAX_EXAMPLES=60 .venv/bin/pytest -n0
tests/api/test_schemathesis.py` (its report in the file `TILTLAB_SCHEMATHESIS_REPORT` names, if
set). It keeps to one worker: with several, Schemathesis' coverage phase builds Hypothesis
strategies in threads at once and, on Python 3.11, stops with its own error ("AST constructor
recursion depth mismatch").

Before the run the daemon holds what the record and diagnosis routes work on: a 3 x 3 stage-grid
job (`/calibrations/1`) and its record (`/records/1`), active, and a diagnosis of it
(`/diagnoses/1`), so the fuzzer reaches those routes' logic (and levelling's) instead of their 404
or 409.

Webhook URLs the generator invents never leave the machine: the daemon's outgoing HTTP goes to a
closed loopback port.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from tests.helpers.daemon import calibrate_and_activate
from tests.helpers.diagnosis import wait_diagnosis
from tests.helpers.running_service import free_port, running_service

SCHEMATHESIS = shutil.which("schemathesis", path=str(Path(sys.executable).parent)) or shutil.which(
    "schemathesis"
)
pytestmark = pytest.mark.skipif(
    SCHEMATHESIS is None, reason="schemathesis is part of the dev extra"
)

REQUEST_TIMEOUT_S = 60.0
PATCHED_TOKEN = "lims-reader"
# the person a record's approval names; the fuzzer's token signs as them
FUZZER_PERSON = {"name": "Dr. Fuzz Example", "function": "Quality manager"}
ACCEPTED_WITH_422 = ("2xx", "3xx", "401", "403", "404", "409", "422", "429", "5xx")
# operations the generator reaches with an id that names nothing (a 404) nearly every time: they
# are given the id of what the daemon holds before the run (_hold_a_record_and_a_diagnosis)
HELD = (
    ("POST /calibrations/{job_id}/cancel", "job_id"),
    ("POST /calibrations/{job_id}/resume", "job_id"),
    ("GET /records/{record_id}/certificate", "record_id"),
    ("GET /records/{record_id}/certificate.html", "record_id"),
    ("POST /records/{record_id}/approve", "record_id"),
    ("POST /records/{record_id}/reject", "record_id"),
    ("POST /diagnoses/{diagnosis_id}/adopt", "diagnosis_id"),
)
# one `[[operations]]` entry per operation, named as Schemathesis names it ("METHOD /path"): in an
# entry, `include-path` and `include-method` would each select on their own (every POST, say)
CONFIG = (
    # `--checks all` also sets a time limit on answers, 10 s unless given: a wall-clock assertion,
    # which no test makes (a loaded machine answered a diagnosis plan in 14.6 s, an idle one in
    # 0.8-1.0 s). It is the request timeout, which fails a request anyway.
    f"""
[checks]
max_response_time = {REQUEST_TIMEOUT_S}
"""
    + "\n".join(
        f"""
[[operations]]
include-name = "{operation}"
checks.positive_data_acceptance.expected-statuses = {list(ACCEPTED_WITH_422)!r}
"""
        for operation in (
            "POST /calibrations",
            "POST /standards",
            "POST /orders",
            "GET /feed",
            "POST /stage/level",
        )
    ).replace("'", '"')
    + f"""
[[operations]]
include-name = "POST /records/{{record_id}}/diagnose"
checks.not_a_server_error.expected-statuses = ["2xx", "3xx", "4xx", "503"]

[[operations]]
include-name = "DELETE /tokens/{{name}}"
enabled = false

[[operations]]
include-name = "PATCH /tokens/{{name}}"
parameters = {{ "path.name" = "{PATCHED_TOKEN}" }}
"""
    + "".join(
        f"""
[[operations]]
include-name = "{operation}"
parameters = {{ "path.{name}" = 1 }}
"""
        for operation, name in HELD
    )
)


def test_every_operation_answers_as_documented(tmp_path: Path) -> None:
    # nothing listens there: deliveries fail, on this machine
    nowhere = f"http://127.0.0.1:{free_port()}"
    data = tmp_path / "data"
    env = {
        "TILTLAB_SIM_SPEED": "20",
        "HTTP_PROXY": nowhere,
        "HTTPS_PROXY": nowhere,
        "NO_PROXY": "",
        "TILTLAB_LAB_NAME": "Inclination Lab GmbH",
        "TILTLAB_LAB_CITY": "Braunschweig",
        "TILTLAB_LAB_COUNTRY_CODE": "DE",
        # the fuzzer's own address sends unknown tokens by the hundred on purpose (ignored_auth)
        "TILTLAB_FAILED_TOKENS_BURST": "100000",
    }
    config = tmp_path / "schemathesis.toml"
    config.write_text(CONFIG)
    with running_service(data, **env) as base:
        admin = {"Authorization": "Bearer " + (data / "admin.token").read_text().strip()}
        made = httpx.post(
            f"{base}/tokens",
            json={"name": "fuzzer", "scopes": ["admin"], "person": FUZZER_PERSON},
            headers=admin,
            timeout=30,
        )
        assert made.status_code == 201, made.text
        patched = httpx.post(
            f"{base}/tokens",
            json={"name": PATCHED_TOKEN, "scopes": ["read"]},
            headers=admin,
            timeout=30,
        )
        assert patched.status_code == 201, patched.text
        _hold_a_record_and_a_diagnosis(base, made.json()["token"])
        r = subprocess.run(
            [
                str(SCHEMATHESIS),
                "--config-file",
                str(config),
                "run",
                f"{base}/openapi.json",
                "-H",
                f"Authorization: Bearer {made.json()['token']}",
                "--checks",
                "all",
                "--phases",
                "examples,coverage,fuzzing,stateful",
                "--max-examples",
                os.environ.get("TILTLAB_SCHEMATHESIS_MAX_EXAMPLES", "5"),
                "--workers",
                "1",
                "--request-timeout",
                str(REQUEST_TIMEOUT_S),
                "--generation-with-security-parameters",
                "false",
            ],
            capture_output=True,
            text=True,
            timeout=1800,
            env={**os.environ, "NO_COLOR": "1"},
            cwd=tmp_path,
        )  # its cache of examples stays out of the repository
    report = r.stdout + r.stderr
    Path(os.environ.get("TILTLAB_SCHEMATHESIS_REPORT", tmp_path / "schemathesis.txt")).write_text(
        report
    )
    assert r.returncode == 0, report[-8000:]
    summary = report.split("SUMMARY")[-1]
    assert "passed" in summary and "unique failures" not in summary and "errored" not in summary, (
        summary
    )
    # every operation was reached with the token
    assert "Authentication failed" not in report, report[-4000:]


def _hold_a_record_and_a_diagnosis(base: str, token: str) -> None:
    """Job 1 (a 3 x 3 stage grid) with its record 1, active (`POST /stage/level` levels with it),
    and diagnosis 1 of it, finished."""
    auth = {"Authorization": f"Bearer {token}"}
    with httpx.Client(base_url=base, timeout=30) as client:
        job = calibrate_and_activate(
            client,
            auth,
            {
                "procedure": "stage-grid",
                "method": "kinematic",
                "grid": {"x_deg": [-4, 4], "y_deg": [-4, 4], "n_x": 3, "n_y": 3},
            },
        )
        assert job["record"]["id"] == 1, job
        diagnosing = client.post(
            "/records/1/diagnose", json={"baseline": "kinematic"}, headers=auth
        )
        assert diagnosing.status_code == 202, diagnosing.text
        diagnosis = wait_diagnosis(client, auth, diagnosing.json()["id"])
        assert diagnosis["id"] == 1 and diagnosis["state"] == "succeeded", diagnosis
