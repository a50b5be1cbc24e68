"""What the LIMS tests share: a reference standard, an order and the people behind the tokens; a
record as a job leaves it; a LIMS's webhook endpoint that checks every signature; the lab's settings
and grid for the flows through the daemon."""

from __future__ import annotations

import http.server
import threading

from standardwebhooks import Webhook

from service.storage.store import Store
from service.storage.tokens import Person
from tests.helpers.certificates import stage_record

STANDARD = {
    "name": "reference inclinometer",
    "serial": "REF-77",
    "certificate_number": "DAkkS-2026-0412",
    "certificate_sha256": "ab" * 32,
    "calibrated_on": "2026-01-10",
    "due_on": "2099-01-10",
    "uncertainty": "0.001 deg (k = 2)",
    "calibrated_by": {
        "name": "Angle Calibration Laboratory AG",
        "accreditation": "D-K-12345-01-00",
        "city": "Hamburg",
        "country_code": "DE",
    },
}
# The people behind the tokens the tests sign with: a record is approved by a person with a
# function.
PEOPLE = {
    "alice": Person("Dr. Alice Example", "Head of Laboratory"),
    "bob": Person("Bob Example", "Deputy Head of Laboratory"),
}
ORDER = {
    "lims_order_id": "LIMS-118",
    "item_serial": "CUST-55",
    "procedure": "stage-grid",
    "method": "homography",
    "due_on": "2026-12-01",
    "customer": {"name": "Survey Ltd", "city": "Berlin", "country_code": "DE"},
}
# The lab as the flows through the daemon configure it, and their grid
LAB = {
    "lab_name": "Inclination Lab GmbH",
    "lab_city": "Braunschweig",
    "lab_country_code": "DE",
    "webhook_retry_base_s": 0.1,
    "webhook_retry_max_s": 0.3,
    "webhook_max_attempts": 1000,
}
GRID = {"x_deg": [-2.0, 2.0], "y_deg": [-2.0, 2.0], "n_x": 3, "n_y": 3}


def measured_record(store: Store, *, started_by: str, order_id: int | None = None, version_of=None):  # type: ignore[no-untyped-def]
    """A record as a job leaves it: real fitted model and validation table, job started by
    `started_by`."""
    device = store.devices.find_device("SCA126T", "SN-4711") or store.devices.add_device(
        "SCA126T", "SN-4711", "measurement_sensor", actor="daemon"
    )
    job = store.jobs.create_job(
        device.id,
        "stage",
        "homography",
        actor=started_by,
        order_id=order_id,
        parameters={"request": {"reference_standards": [1]}},
    )
    store.jobs.start_job(job.id, actor="daemon")
    r = stage_record("homography")
    record = store.records.add_record(
        device.id,
        "stage",
        "homography",
        r["model"],
        operator=started_by,
        job_id=job.id,
        validation=r["validation"],
        temp_c=20.4,
        raw_data={"conditions": {"firmware": {"measurement_sensor": "2.3.1"}}},
    )
    store.jobs.succeed_job(job.id, actor="daemon")
    return record


class Receiver:
    """A LIMS's webhook endpoint on 127.0.0.1: verifies each signature, answers 503 while `down`."""

    def __init__(self) -> None:
        self.secret: str | None = None
        self.down = False
        self.ids: list[str] = []
        self.bodies: list[dict] = []  # the events as delivered
        self.bad: list[str] = []
        self.refused = 0
        receiver = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                body = self.rfile.read(int(self.headers["content-length"]))
                if receiver.down:
                    receiver.refused += 1
                    self.send_response(503)
                    self.end_headers()
                    return
                try:
                    event = Webhook(receiver.secret).verify(body, dict(self.headers))
                    assert event["id"] == self.headers["webhook-id"]
                    receiver.ids.append(event["id"])
                    receiver.bodies.append(event)
                except Exception as exc:  # noqa: BLE001 - recorded for the test to fail on
                    receiver.bad.append(repr(exc))
                self.send_response(204)
                self.end_headers()

            def log_message(self, *args) -> None:  # type: ignore[no-untyped-def]
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_port}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
