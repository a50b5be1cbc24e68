"""Schemathesis against the running daemon: every operation answers what its OpenAPI document says,
with every check this Schemathesis version offers (`--checks all`), in its examples, coverage,
fuzzing and stateful phases.

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
* `positive_data_acceptance` also takes 422 on four operations, where a schema-valid request can be
  refused for what JSON Schema cannot state: `POST /calibrations` (the grid must lie within the
  bench's travel and hold as many points as the method needs, a product of two counts; the standards
  and order it names must exist and be valid: the lab's stored data), `POST /standards` (`due_on`
  must come after `calibrated_on`: two values compared), `POST /orders` (an `Idempotency-Key` used
  before for another body is 422, as the IETF draft on that header asks: the lab's stored data) and
  `GET /feed` (a cursor must be one the feed gave out: it is opaque). Everything else the routes
  enforce the document states (docs/api.md, "The OpenAPI document and request validation").

A longer, concurrent run (more thread-safety and state bugs surface with several workers):
`TILTLAB_SCHEMATHESIS_MAX_EXAMPLES=50 TILTLAB_SCHEMATHESIS_WORKERS=4 .venv/bin/pytest -n0
tests/api/test_schemathesis.py`, its report in `TILTLAB_SCHEMATHESIS_REPORT` if set.

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

from tests.helpers.running_service import free_port, running_service

SCHEMATHESIS = shutil.which("schemathesis", path=str(Path(sys.executable).parent)) or shutil.which(
    "schemathesis"
)
pytestmark = pytest.mark.skipif(
    SCHEMATHESIS is None, reason="schemathesis is part of the dev extra"
)

PATCHED_TOKEN = "lims-reader"
# the person a record's approval names; the fuzzer's token signs as them
FUZZER_PERSON = {"name": "Dr. Fuzz Example", "function": "Quality manager"}
ACCEPTED_WITH_422 = ("2xx", "3xx", "401", "403", "404", "409", "422", "429", "5xx")
# one `[[operations]]` entry per operation, named as Schemathesis names it ("METHOD /path"): in an
# entry, `include-path` and `include-method` would each select on their own (every POST, say)
CONFIG = (
    "\n".join(
        f"""
[[operations]]
include-name = "{operation}"
checks.positive_data_acceptance.expected-statuses = {list(ACCEPTED_WITH_422)!r}
"""
        for operation in ("POST /calibrations", "POST /standards", "POST /orders", "GET /feed")
    ).replace("'", '"')
    + f"""
[[operations]]
include-name = "DELETE /tokens/{{name}}"
enabled = false

[[operations]]
include-name = "PATCH /tokens/{{name}}"
parameters = {{ "path.name" = "{PATCHED_TOKEN}" }}
"""
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
                os.environ.get("TILTLAB_SCHEMATHESIS_WORKERS", "1"),
                "--request-timeout",
                "60",
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
