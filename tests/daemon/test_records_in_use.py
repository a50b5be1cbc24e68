"""Records in use on the daemon: a rejected record is withdrawn and never activated again, a record
whose stored content was altered is refused at start-up and on activation, and /tilt (and the
reading stream) say whether a reading lies inside the range the record was calibrated over."""

from __future__ import annotations

import json

import sqlalchemy as sa

from service import cli
from service.storage.tokens import Person
from tests.helpers.daemon import admin_headers, fresh_tilt, make_client, wait_job
from tests.helpers.waiting import eventually

GRID = {"x_deg": [-1.0, 1.0], "y_deg": [-1.0, 1.0], "n_x": 3, "n_y": 3}
# room for a loaded machine at 20x
SETTLE = {"tolerance_deg": 0.002, "window_s": 2.0, "timeout_s": 600.0}


def _tilt_when(client, h, ok, timeout_s: float = 30.0) -> dict:  # type: ignore[no-untyped-def]
    """A fresh /tilt for which `ok` holds (the stage has arrived and a new reading been taken),
    within a deadline."""
    return eventually(
        lambda: fresh_tilt(client, h),
        until=ok,
        timeout_s=timeout_s,
        every_s=0.05,
        what="/tilt satisfying the condition",
    )


def _stream_reading(client, token: str, ok, limit: int = 400) -> dict:  # type: ignore[no-untyped-def]
    with client.websocket_connect(f"/ws/readings?token={token}&rate_hz=20") as ws:
        snapshot = ws.receive_json()
        assert snapshot["type"] == "snapshot" and "in_calibrated_range" in snapshot
        for _ in range(limit):
            msg = ws.receive_json()
            if msg["type"] == "reading" and ok(msg):
                ws.close()
                return msg
    raise AssertionError("no reading on the stream satisfied the condition")


def test_calibrated_range_draft_status_and_rejection_of_the_active_record(tmp_path) -> None:  # type: ignore[no-untyped-def]
    with make_client(tmp_path) as client:
        store = client.app.state.store
        h = {"admin": admin_headers(tmp_path)}
        for name in ("alice", "bob"):
            person = Person(f"{name.title()} Example", "Calibration Engineer")
            secret = store.tokens.create_token(name, "admin", actor="admin", person=person)[1]
            h[name] = {"Authorization": f"Bearer {secret}"}
        token = h["alice"]["Authorization"].split()[1]
        r = client.post(
            "/calibrations",
            headers=h["alice"],
            json={
                "procedure": "stage-grid",
                "method": "kinematic",
                "grid": GRID,
                "samples_per_point": 8,
                "validation": {"n_points": 2},
                "settle": SETTLE,
            },
        )
        assert r.status_code == 202, r.text
        job = wait_job(client, r.json()["id"], h["alice"])
        assert job["state"] == "succeeded", job
        rid = job["record"]["id"]

        # the calibrated range: the reference sensor's readings over the fitted grid (table tilt ≈
        # stage + desk)
        record = client.get(f"/records/{rid}", headers=h["alice"]).json()
        rng = record["calibrated_range"]
        assert rng["frame"] == "reference_sensor", rng
        model = client.get(f"/records/{rid}/model", headers=h["alice"]).json()
        assert model["fit"]["table_tilt_range_deg"] == {"x": rng["x_deg"], "y": rng["y_deg"]}
        for axis in ("x_deg", "y_deg"):
            lo, hi = rng[axis]
            assert 1.8 < hi - lo < 2.2 and abs((lo + hi) / 2) < 0.5, rng

        # a draft may be used, and /tilt says it is a draft
        assert client.post(f"/records/{rid}/activate", headers=h["alice"]).status_code == 200
        assert (
            client.post(
                "/stage/move", headers=h["alice"], json={"x_deg": 0.0, "y_deg": 0.0}
            ).status_code
            == 200
        )
        t = _tilt_when(
            client,
            h["alice"],
            lambda t: t["table_tilt"] is not None and t["in_calibrated_range"] is True,
        )
        calibration = dict(t["calibration"])
        # one reading's noise: estimated from the readings the record's job stored at its points
        assert calibration.pop("reading_noise").startswith("pooled within-point standard deviation")
        assert calibration == {
            "record_id": rid,
            "version": record["version"],
            "method": "kinematic",
            "status": "draft",
        }
        assert "outside the calibrated range" not in t["note"]

        # outside the range: still served, flagged, and the note says so
        assert (
            client.post(
                "/stage/move", headers=h["alice"], json={"x_deg": 1.8, "y_deg": 0.0}
            ).status_code
            == 200
        )
        t = _tilt_when(
            client,
            h["alice"],
            lambda t: t["table_tilt"] is not None and t["table_tilt"]["x_deg"] > 1.5,
        )
        assert t["in_calibrated_range"] is False and t["table_tilt"]["x_deg"] > rng["x_deg"][1], t
        assert "outside the calibrated range" in t["note"], t
        msg = _stream_reading(
            client, token, lambda m: m["table_tilt"] is not None and m["table_tilt"]["x_deg"] > 1.5
        )
        assert msg["in_calibrated_range"] is False, msg

        # rejecting the active record withdraws it: /tilt corrects nothing and says why; levelling
        # is refused
        r = client.post(
            f"/records/{rid}/reject",
            json={"reason": "reference sensor was out of date"},
            headers=h["bob"],
        )
        assert r.status_code == 200, r.text
        got = client.get(f"/records/{rid}", headers=h["alice"]).json()
        assert got["status"] == "rejected" and got["active"] is False, got
        t = fresh_tilt(client, h["alice"])
        assert (
            t["table_tilt"] is None
            and t["calibration"] is None
            and t["in_calibrated_range"] is None
        ), t
        assert "rejected" in t["note"] and "reference sensor was out of date" in t["note"], t
        r = client.post(
            "/stage/level",
            headers=h["alice"],
            json={"x_deg": 0.0, "y_deg": 0.0, "tolerance_deg": 0.01, "max_iterations": 3},
        )
        assert r.status_code == 409 and r.headers["content-type"].startswith(
            "application/problem+json"
        ), r.text
        assert "rejected" in r.json()["detail"]
        # and a rejected record cannot be activated again
        r = client.post(f"/records/{rid}/activate", headers=h["alice"])
        assert r.status_code == 409 and "rejected" in r.json()["detail"], r.text
        assert client.get(f"/records/{rid}", headers=h["alice"]).json()["active"] is False
        assert fresh_tilt(client, h["alice"])["table_tilt"] is None


def _offline_model(tmp_path) -> dict:  # type: ignore[no-untyped-def]
    """A stage model fitted offline on a simulated run (what a record made elsewhere would hold)."""
    data, out = tmp_path / "run.csv", tmp_path / "model.json"
    assert cli.main(["simulate", "--scenario", "seed000", "--out", str(data)]) == 0
    assert (
        cli.main(
            [
                "calibrate",
                "--kind",
                "stage",
                "--method",
                "kinematic",
                "--input",
                str(data),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    return json.loads(out.read_text())


def _tamper(engine: sa.Engine, record_id: int) -> None:
    """Edit a stored model directly in the database, as someone with the file could."""
    with engine.begin() as conn:
        for (name,) in conn.exec_driver_sql(
            "SELECT name FROM sqlite_master WHERE type = 'trigger' AND tbl_name = "
            "'calibration_records'"
        ).all():
            conn.exec_driver_sql(f"DROP TRIGGER {name}")
        model = json.loads(
            conn.execute(
                sa.text("SELECT model FROM calibration_records WHERE id = :i"), {"i": record_id}
            ).scalar_one()
        )
        first = next(iter(model["parameters"]))
        model["parameters"][first]["value"] += 0.05
        conn.execute(
            sa.text("UPDATE calibration_records SET model = :m WHERE id = :i"),
            {"m": json.dumps(model), "i": record_id},
        )


def test_an_altered_active_record_is_refused_at_start_up_and_on_activation(tmp_path) -> None:  # type: ignore[no-untyped-def]
    model = _offline_model(tmp_path)
    with make_client(tmp_path) as client:
        h = admin_headers(tmp_path)
        store = client.app.state.store
        store.tokens.set_person(
            "admin", Person("Dr. Alice Example", "Head of Laboratory"), actor="setup"
        )
        meas = client.app.state.bench.device_ids["measurement_sensor"]
        good = store.records.add_record(meas, "stage", "kinematic", model, operator="alice")
        other = store.records.add_record(meas, "stage", "kinematic", model, operator="alice")
        assert client.post(f"/records/{good.id}/activate", headers=h).status_code == 200
        assert fresh_tilt(client, h)["calibration"]["record_id"] == good.id
        # approved by someone other than its operator: /tilt's calibration says so from then on
        r = client.post(
            f"/records/{good.id}/approve", json={"meaning": "approval", "note": "ok"}, headers=h
        )
        assert r.status_code == 200, r.text
        assert fresh_tilt(client, h)["calibration"]["status"] == "approved"
        _tamper(store.engine, good.id)
        _tamper(store.engine, other.id)
        # activation checks the hash: the altered record is refused, whether active already or not
        for rid in (good.id, other.id):
            r = client.post(f"/records/{rid}/activate", headers=h)
            assert r.status_code == 409 and "SHA-256" in r.json()["detail"], r.text
    with make_client(tmp_path) as client:  # the daemon starts again on the altered database
        t = fresh_tilt(client, h)
        assert t["table_tilt"] is None and t["calibration"] is None, t
        assert f"record {good.id}" in t["note"] and "does not match its SHA-256" in t["note"], t
        r = client.post(
            "/stage/level",
            headers=h,
            json={"x_deg": 0.0, "y_deg": 0.0, "tolerance_deg": 0.01, "max_iterations": 3},
        )
        assert r.status_code == 409, r.text
        r = client.post(f"/records/{good.id}/activate", headers=h)
        assert r.status_code == 409 and "SHA-256" in r.json()["detail"], r.text
