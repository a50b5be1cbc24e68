"""A LIMS integrator's first hour: a client generated from the running daemon's /openapi.json with
openapi-python-client drives the whole LIMS flow (standards, an order, a job, approval by a second
person, the certificate, the feed), and reads refused requests as typed problems."""

from __future__ import annotations

import datetime as dt
import importlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import httpx
import pytest

from service.lims import dcc
from tests.helpers.running_service import running_service
from tests.helpers.waiting import eventually

GENERATOR = shutil.which(
    "openapi-python-client", path=str(Path(sys.executable).parent)
) or shutil.which("openapi-python-client")
pytestmark = pytest.mark.skipif(
    GENERATOR is None, reason="openapi-python-client is part of the dev extra"
)

LAB = {
    "TILTLAB_LAB_NAME": "Inclination Lab GmbH",
    "TILTLAB_LAB_CITY": "Braunschweig",
    "TILTLAB_LAB_COUNTRY_CODE": "DE",
    "TILTLAB_SIM_SPEED": "20",
}


def generate(base: str, out: Path) -> ModuleType:
    """The client package, generated from the document the daemon serves, and imported."""
    spec = out / "openapi.json"
    spec.write_text(httpx.get(f"{base}/openapi.json", timeout=30).text)
    env = {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
    }
    r = subprocess.run(
        [
            str(GENERATOR),
            "generate",
            "--path",
            str(spec),
            "--output-path",
            str(out / "tiltlab_client"),
            "--meta",
            "none",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    sys.path.insert(0, str(out))
    importlib.invalidate_caches()
    return importlib.import_module("tiltlab_client")


def test_a_generated_client_drives_the_lims_flow_and_reads_problems(tmp_path: Path) -> None:
    data = tmp_path / "data"
    with running_service(data, **LAB) as base:
        pkg = generate(base, tmp_path)
        try:
            _lims_flow(pkg, base, (data / "admin.token").read_text().strip())
        finally:
            sys.path.remove(str(tmp_path))
            for name in [
                n for n in sys.modules if n == "tiltlab_client" or n.startswith("tiltlab_client.")
            ]:
                del sys.modules[name]


def _lims_flow(pkg: ModuleType, base: str, admin_token: str) -> None:
    m = importlib.import_module("tiltlab_client.models")
    tokens = importlib.import_module("tiltlab_client.api.tokens.create_tokens_post")
    lims = {
        name: importlib.import_module(f"tiltlab_client.api.lims.{name}")
        for name in (
            "add_standard_standards_post",
            "create_order_orders_post",
            "approve_records_record_id_approve_post",
            "certificate_records_record_id_certificate_get",
            "feed_feed_get",
        )
    }
    start = importlib.import_module("tiltlab_client.api.calibrations.start_calibrations_post")
    read_job = importlib.import_module(
        "tiltlab_client.api.calibrations.read_calibrations_job_id_get"
    )
    read_record = importlib.import_module("tiltlab_client.api.records.read_records_record_id_get")

    admin = pkg.AuthenticatedClient(base_url=base, token=admin_token, timeout=httpx.Timeout(60.0))
    people = {}
    for name in ("alice", "bob"):
        made = tokens.sync(
            client=admin,
            body=m.NewToken(
                name=name,
                scopes=[m.NewTokenScopesItem("admin")],
                person=m.PersonIn(name=f"{name.title()} Example", function="Calibration Engineer"),
            ),
        )
        assert isinstance(made, m.CreatedToken), made
        people[name] = pkg.AuthenticatedClient(
            base_url=base, token=made.token, timeout=httpx.Timeout(60.0)
        )

    standard = lims["add_standard_standards_post"].sync(
        client=admin,
        body=m.StandardIn(
            name="reference inclinometer",
            serial="REF-77",
            certificate_number="DAkkS-2026-0412",
            certificate_sha256="ab" * 32,
            calibrated_on=dt.date(2026, 1, 10),
            due_on=dt.date(2099, 1, 10),
            expanded_uncertainty_deg=0.002,
            calibrated_by=m.CalibratedByIn(
                name="Angle Calibration Laboratory AG", country_code="DE"
            ),
        ),
    )
    assert isinstance(standard, m.Standard), standard
    order = lims["create_order_orders_post"].sync(
        client=admin,
        idempotency_key="lims-118",
        body=m.OrderIn(
            lims_order_id="LIMS-118",
            item_serial="CUST-55",
            procedure=m.OrderInProcedure("stage-grid"),
            method="kinematic",
            customer=m.CustomerIn(name="Survey Ltd", city="Berlin", country_code="DE"),
            item_manufacturer="Example Sensors",
            item_model="NS-25",
        ),
    )
    assert isinstance(order, m.Order), order

    refused = start.sync_detailed(
        client=people["alice"],
        body=m.CalibrationRequest(
            procedure=m.CalibrationRequestProcedure("stage-grid"),
            method="kinematic",
            grid=m.Grid(x_deg=[-2.0, 2.0], y_deg=[-2.0, 2.0], n_x=1, n_y=1),
        ),
    )
    assert refused.status_code == 422
    assert isinstance(refused.parsed, m.Problem), refused.content  # a 422 read as a typed problem
    assert (
        isinstance(refused.parsed.field, str)
        and "grid" in refused.parsed.field
        and refused.parsed.detail
    )

    job = start.sync(
        client=people["alice"],
        idempotency_key="cal-118",
        body=m.CalibrationRequest(
            procedure=m.CalibrationRequestProcedure("stage-grid"),
            method="kinematic",
            grid=m.Grid(x_deg=[-2.0, 2.0], y_deg=[-2.0, 2.0], n_x=3, n_y=3),
            samples_per_point=8,
            validation=m.Validation(n_points=3),
            reference_standards=[standard.id],
            order_id=order.id,
            # 2-s windows: a loaded machine lags the sped-up readings by more than the default
            # window
            settle=m.Settle(tolerance_deg=0.002, window_s=2.0, timeout_s=600.0),
        ),
    )
    assert isinstance(job, m.Job), job
    job_id = job.id

    def job_now() -> m.Job:
        read = read_job.sync(job_id, client=admin)
        assert isinstance(read, m.Job), read
        return read

    job = eventually(
        job_now,
        until=lambda job: str(job.state) in ("succeeded", "failed", "cancelled"),
        timeout_s=300,
        every_s=0.5,
        what=f"job {job_id} ended",
    )
    assert str(job.state) == "succeeded", job.error
    record_id = job.record.id

    record = read_record.sync(record_id, client=admin)
    assert isinstance(record, m.Record) and str(record.status) == "draft", record
    approve = lims["approve_records_record_id_approve_post"]
    own = approve.sync_detailed(record_id, client=people["alice"], body=m.ApproveIn(note="mine"))
    # who started the job may not approve it
    assert own.status_code == 403 and isinstance(own.parsed, m.Problem)
    assert (
        approve.sync_detailed(
            record_id, client=people["bob"], body=m.ApproveIn(note="ok")
        ).status_code
        == 200
    )
    assert str(read_record.sync(record_id, client=admin).status) == "approved"

    certificate = lims["certificate_records_record_id_certificate_get"].sync_detailed(
        record_id, client=admin
    )
    assert certificate.status_code == 200 and certificate.headers["content-type"].startswith(
        "application/xml"
    )
    assert dcc.certificate_errors(certificate.content) == []
    assert b"CUST-55" in certificate.content

    feed = lims["feed_feed_get"].sync(client=admin, limit=1000)
    assert isinstance(feed, m.Feed), feed
    types = {event.type_ for event in feed.events}
    for wanted in (
        "order.created",
        "job.state",
        "record.created",
        "record.approved",
        "certificate.issued",
    ):
        assert wanted in types, wanted
    json.dumps(feed.to_dict())  # a typed answer turns back into the JSON it came from
