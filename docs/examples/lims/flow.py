"""The complete LIMS example of docs/lims.md, run against an in-process daemon on its simulated
stage bench (with an ambient sensor, 20 times real time): a standard naming who calibrated it, an
order with a specification, a job, approval by a named person, the certificate. Writes what each
step answered into OUT (default: this folder):

    python docs/examples/lims/flow.py [--out DIR]

Files: requests.json (every request and the answer's status and body), record.json, order.json,
certificate.xml, certificate.html, certificate_issued.json (the feed event), budget.md (the budget
as a table). The signing key is a new self-signed one on every run, so certificate.xml differs
between runs in its signature.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import tempfile
import time
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import NameOID
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.config import Settings
from service.storage.tokens import Person

HERE = Path(__file__).resolve().parent
PEOPLE = {
    "alice": Person("Dr. Alice Example", "Head of Laboratory"),
    "bob": Person("Bob Example", "Deputy Head of Laboratory"),
}
STANDARD = {
    "name": "reference inclinometer",
    "serial": "REF-77",
    "model": "NS-25",
    "certificate_number": "DAkkS-2026-0412",
    "certificate_sha256": "ab" * 32,
    "calibrated_on": "2026-01-10",
    "due_on": "2099-01-10",
    "expanded_uncertainty_deg": 0.001,
    "coverage_factor": 2,
    "uncertainty": "0.001 deg (k = 2)",
    "calibrated_by": {
        "name": "Angle Calibration Laboratory AG",
        "accreditation": "D-K-12345-01-00",
        "city": "Hamburg",
        "country_code": "DE",
    },
}
ORDER = {
    "lims_order_id": "LIMS-2026-118",
    "item_serial": "SN-4711",
    "item_manufacturer": "Example Sensors",
    "item_model": "NS-25",
    "customer": {"name": "Survey Instruments Ltd", "city": "Berlin", "country_code": "DE"},
    "procedure": "stage-grid",
    "method": "kinematic",
    "due_on": "2026-12-01",
    "specification": {
        "max_permissible_error_deg": 0.5,
        "decision_rule": "guarded_acceptance",
        "guard_band_fraction": 1.0,
    },
}
JOB = {
    "procedure": "stage-grid",
    "method": "kinematic",
    "grid": {"x_deg": [-6.0, 6.0], "y_deg": [-6.0, 6.0], "n_x": 5, "n_y": 5},
    "samples_per_point": 10,
    "validation": {"n_points": 5},
    "settle": {"tolerance_deg": 0.002, "window_s": 2.0, "timeout_s": 600.0},
}


def _signing_files(where: Path) -> tuple[Path, Path]:
    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    name = x509.Name(
        [x509.NameAttribute(NameOID.COMMON_NAME, "Inclination Laboratory certificate signing")]
    )
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(days=1))
        .not_valid_after(now + dt.timedelta(days=365))
        .sign(key, hashes.SHA256())
    )
    (where / "key.pem").write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    (where / "cert.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return where / "key.pem", where / "cert.pem"


def _dof(nu: float | None) -> str:
    return "∞" if nu is None or not math.isfinite(nu) else f"{nu:.0f}"


def budget_table(budget: dict[str, Any]) -> str:
    """The record's budget as docs/lims.md shows it: each result's components, then their
    combination."""
    rows = ["| result | component | standard uncertainty u | ν |", "| --- | --- | --- | --- |"]
    for r in budget["results"]:
        unit = "°" if r["unit"] == "deg" else f" {r['unit']}"
        for i, c in enumerate(r["contributions"]):
            what = (
                "the fit (parameters' covariance and reading noise)"
                if c["source"] == "fit"
                else c["name"]
            )
            rows.append(
                f"| {r['quantity'] if i == 0 else ''} | {what} | "
                f"{c['standard_uncertainty']:.2g}{unit} | {_dof(c.get('dof'))} |"
            )
        rows.append(
            f"| | **combined**: u_c = {r['standard_uncertainty']:.2g}{unit}, ν_eff = "
            f"{_dof(r.get('dof_eff'))}, "
            f"k = {r['coverage_factor']:.3g}, **expanded uncertainty U = "
            f"{r['expanded_uncertainty']:.2g}{unit}** | | |"
        )
    return "\n".join(rows) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=HERE)
    out = parser.parse_args().out
    out.mkdir(parents=True, exist_ok=True)
    log: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="tiltlab-lims-example-") as tmp:
        key, cert = _signing_files(Path(tmp))
        settings = Settings(
            data_dir=Path(tmp) / "data",
            sim_speed=20.0,
            sim_transport="loopback",
            sim_ambient_sensor=True,
            require_conditions=True,
            lab_name="Inclination Laboratory Example GmbH",
            lab_city="Braunschweig",
            lab_country_code="DE",
            lab_accreditation="D-K-00000-01-00",
            certificate_signing_key=str(key),
            certificate_signing_cert=str(cert),
        )
        with TestClient(create_app(settings)) as client:
            admin = {
                "Authorization": "Bearer " + (settings.data_dir / "admin.token").read_text().strip()
            }

            def call(
                method: str, path: str, who: dict[str, str], body: Any = None, **headers: str
            ) -> Any:
                r = client.request(method, path, json=body, headers={**who, **headers})
                answer = (
                    r.json()
                    if r.headers.get("content-type", "").startswith("application/")
                    and "json" in r.headers["content-type"]
                    else None
                )
                log.append(
                    {
                        "request": f"{method} {path}",
                        "body": body,
                        "status": r.status_code,
                        "answer": answer,
                    }
                )
                if r.status_code >= 400:
                    raise SystemExit(f"{method} {path}: {r.status_code} {r.text}")
                return answer if answer is not None else r

            tokens = {}
            for name, scopes in (("alice", ["admin"]), ("bob", ["admin"]), ("lims", ["operate"])):
                person = PEOPLE.get(name)
                body = {
                    "name": name,
                    "scopes": scopes,
                    **(
                        {"person": {"name": person.name, "function": person.function}}
                        if person
                        else {}
                    ),
                }
                tokens[name] = {
                    "Authorization": "Bearer " + call("POST", "/tokens", admin, body)["token"]
                }
            std = call("POST", "/standards", tokens["alice"], STANDARD)
            order = call(
                "POST", "/orders", tokens["lims"], ORDER, **{"Idempotency-Key": "lims-2026-118"}
            )
            job = call(
                "POST",
                "/calibrations",
                tokens["alice"],
                {**JOB, "reference_standards": [std["id"]], "order_id": order["id"]},
            )
            while job["state"] not in ("succeeded", "failed", "cancelled"):
                time.sleep(0.5)
                job = client.get(f"/calibrations/{job['id']}", headers=admin).json()
            if job["state"] != "succeeded":
                raise SystemExit(f"job {job['id']} {job['state']}: {job['error']}")
            rid = job["record"]["id"]
            call(
                "POST",
                f"/records/{rid}/approve",
                tokens["bob"],
                {"meaning": "approval", "note": "residuals fine"},
            )
            xml = call("GET", f"/records/{rid}/certificate", tokens["lims"]).content
            page = call("GET", f"/records/{rid}/certificate.html", tokens["lims"]).text
            record = call("GET", f"/records/{rid}", tokens["lims"])
            order = call("GET", f"/orders/{order['id']}", tokens["lims"])
            feed = call("GET", "/feed?limit=1000", tokens["lims"])
    for entry in log:  # a token's text is shown once: it is not kept in the example either
        if isinstance(entry["answer"], dict) and "token" in entry["answer"]:
            entry["answer"]["token"] = "tl_..."
    (out / "requests.json").write_text(json.dumps(log, indent=1, default=str) + "\n")
    (out / "record.json").write_text(json.dumps(record, indent=1) + "\n")
    (out / "order.json").write_text(json.dumps(order, indent=1) + "\n")
    (out / "certificate.xml").write_bytes(xml)
    (out / "certificate.html").write_text(page)
    issued = [e for e in feed["events"] if e["type"] == "certificate.issued"]
    (out / "certificate_issued.json").write_text(json.dumps(issued[0], indent=1) + "\n")
    (out / "budget.md").write_text(budget_table(record["budget"]))
    print(
        f"record {rid}: conformity {record['conformity']['x']} (x), "
        f"{record['conformity']['y']} (y); "
        f"files in {out}"
    )


if __name__ == "__main__":
    main()
