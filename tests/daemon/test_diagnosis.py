"""Diagnosis end to end on simulated benches: calibrate through the daemon, run the discrepancy workflow on the
stored record, the hidden effect is named and the gap closes to the noise; adopting it gives a record that
levels closer to the simulator's truth. A bench with nothing hidden names nothing and has nothing to adopt."""

from __future__ import annotations

import json
import time

from tests.benches.conftest import scenario
from tests.daemon.conftest import admin_headers, make_client, wait_job

# 7 x 7 points 2.4 deg apart: the 180:1 upper worm (2-deg period) and the 360:1 lower one (1 deg) are each
# sampled at five phases
GRID = {"x_deg": [-7.2, 7.2], "y_deg": [-7.2, 7.2], "n_x": 7, "n_y": 7}
BODY = {"procedure": "stage-grid", "method": "kinematic", "grid": GRID, "samples_per_point": 8,
        "validation": {"n_points": 4}, "settle": {"tolerance_deg": 0.005, "window_s": 0.5, "timeout_s": 60}}
PERIODIC_X = {"periodic_error": {"x_amp_deg": 0.010, "x_phase_deg": 40.0}}
# Targets between the grid points (none of them is a grid point)
TARGETS = [(1.3, -2.1), (-4.7, 3.3), (5.9, 0.7), (-2.6, -5.4), (3.5, 4.9), (-6.1, -0.9)]


def wait_diagnosis(client, h, diagnosis_id: int, timeout_s: float = 300.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        d = client.get(f"/diagnoses/{diagnosis_id}", headers=h).json()
        if d["state"] in ("succeeded", "failed"):
            return d
        assert time.monotonic() < deadline, d
        time.sleep(0.2)


def start_daemon(tmp_path, effects: dict | None):
    path = tmp_path / "bench.json"
    path.write_text(json.dumps(scenario("180-360", effects)))
    # 5 times real time: a loaded machine still reads the sensors within a settling window
    return make_client(tmp_path, bench_scenario=str(path), sim_speed=5.0)


def calibrate(client, h) -> dict:
    r = client.post("/calibrations", headers=h, json=BODY)
    assert r.status_code == 202, r.text
    job = wait_job(client, r.json()["id"], h)
    assert job["state"] == "succeeded", job
    return job["record"]


def diagnose(client, h, record_id: int, **body) -> dict:
    r = client.post(f"/records/{record_id}/diagnose", headers=h, json={"sensor": "ref", "baseline": "kinematic", **body})
    assert r.status_code == 202, r.text
    assert r.headers["location"] == f"/diagnoses/{r.json()['id']}"
    assert r.json()["record_id"] == record_id and r.json()["state"] in ("queued", "running", "succeeded")
    d = wait_diagnosis(client, h, r.json()["id"])
    assert d["state"] == "succeeded", d
    return d


def test_periodic_error_named_and_gap_closed_to_the_noise(tmp_path):
    with start_daemon(tmp_path, PERIODIC_X) as client:
        h = admin_headers(tmp_path)
        rec = calibrate(client, h)
        d = diagnose(client, h, rec["id"])
        assert "periodic_error" in d["named_effects"], d
        assert d["gap_after_deg"]["rms"] <= 1.5 * d["noise_deg"], d
        assert d["gap_before_deg"]["rms"] > 2 * d["gap_after_deg"]["rms"], d
        assert d["gap_after_deg"]["max"] >= d["gap_after_deg"]["rms"] > 0
        step = next(s for s in d["effects"] if s["effect"] == "periodic_error")
        amp = step["magnitude"]["x_amp_deg"]
        assert abs(amp["value"] - 0.010) <= 4 * amp["uncertainty"] + 0.001, step
        assert step["evidence"]["p_value"] < 0.01
        page = client.get(f"/diagnoses/{d['id']}/report", headers=h)
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert "periodic_error" in page.text
        listed = client.get("/diagnoses", headers=h, params={"record": rec["id"]}).json()["diagnoses"]
        assert [x["id"] for x in listed] == [d["id"]]
        events = client.get("/feed", headers=h, params={"limit": 500}).json()["events"]
        finished = [e for e in events if e["type"] == "diagnosis.finished"]
        assert finished and finished[-1]["data"]["diagnosis_id"] == d["id"]
        assert finished[-1]["data"]["named_effects"] == d["named_effects"]


def test_bad_requests_name_the_field(tmp_path):
    with start_daemon(tmp_path, None) as client:
        h = admin_headers(tmp_path)
        assert client.post("/records/999/diagnose", headers=h, json={}).status_code == 404
        assert client.get("/diagnoses/999", headers=h).status_code == 404
        rec = calibrate(client, h)
        r = client.post(f"/records/{rec['id']}/diagnose", headers=h, json={"sensor": "both"})
        assert r.status_code == 422 and "sensor" in r.text
        r = client.post(f"/records/{rec['id']}/diagnose", headers=h, json={"baseline": "cubic"})
        assert r.status_code == 422 and "baseline" in r.text
        assert client.get("/diagnoses", headers=h).json()["diagnoses"] == []
