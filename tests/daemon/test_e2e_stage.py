"""End to end on the simulated stage bench: calibrate, activate, corrected tilt against the truth,
level."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service import cli
from tests.helpers.daemon import fresh_tilt, wait_bench_seconds, wait_job

GRID = {"x_deg": [-2.0, 2.0], "y_deg": [-2.0, 2.0], "n_x": 3, "n_y": 3}


def sim_temp(client) -> float:
    return client.app.state.bench.sim.world.temp_c()


@pytest.mark.parametrize("method", ["kinematic", "homography"])
def test_calibrate_activate_tilt_and_level(daemon, method, tmp_path):
    client, h = daemon
    r = client.post(
        "/calibrations",
        headers=h,
        json={
            "procedure": "stage-grid",
            "method": method,
            "grid": GRID,
            "samples_per_point": 8,
            "validation": {"n_points": 3},
        },
    )
    assert r.status_code == 202, r.text
    assert r.headers["location"] == f"/calibrations/{r.json()['id']}"
    job = wait_job(client, r.json()["id"], h)
    assert job["state"] == "succeeded", job
    assert job["progress"] == {"points_done": 12, "points_total": 12, "phase": "done"}
    assert job["validation"]["n_points"] == 3 and job["validation"]["rms_deg"] < 0.01
    rec = job["record"]
    conditions = client.get(f"/records/{rec['id']}", headers=h).json()
    assert conditions["temp_c"] == pytest.approx(sim_temp(client), abs=0.5), conditions
    assert client.post(f"/records/{rec['id']}/activate", headers=h).status_code == 200
    sim = client.app.state.bench.sim
    for pose in [(0.0, 0.0), (1.5, -1.0), (-1.2, 1.7)]:
        assert (
            client.post(
                "/stage/move", headers=h, json={"x_deg": pose[0], "y_deg": pose[1]}
            ).status_code
            == 200
        )
        wait_bench_seconds(client.app.state.bench, 6.0)  # the sensors' readings after the move
        t = fresh_tilt(client, h)
        truth = sim.world.true_tilt_deg()
        assert t["table_tilt"] is not None, t
        assert (
            abs(t["table_tilt"]["x_deg"] - truth[0]) < 0.01
            and abs(t["table_tilt"]["y_deg"] - truth[1]) < 0.01
        ), (t, truth)
        # coverage factors from the effective degrees of freedom: Student's t for 95 %, above the
        # normal 1.96
        tt = t["table_tilt"]
        assert (
            tt["coverage_probability"] == 0.95 and 1.96 <= tt["k"] < 2.6 and 1.96 <= tt["k_y"] < 2.6
        ), tt
        assert tt["u_x_deg"] > 0 and tt["u_y_deg"] > 0
        # the sensors' temperature (asked for by 0x06 at every point and now and then) comes with
        # the tilt
        assert t["temp_c"] == pytest.approx(sim.world.temp_c(), abs=0.5), t
        assert t["calibration"]["record_id"] == rec["id"]
    for target in [(0.0, 0.0), (1.0, 0.5), (-0.8, -1.2)]:
        r = client.post(
            "/stage/level",
            headers=h,
            json={
                "x_deg": target[0],
                "y_deg": target[1],
                # twice the stage's repeatability (2.5 mdeg per axis): one move meets it on both
                # axes about 0.91 of the time, so the loop is given room for the unlucky ones
                "tolerance_deg": 0.005,
                "max_iterations": 8,
            },
        )
        assert r.status_code == 200, r.text
        out = r.json()
        assert out["within_tolerance"], out
        truth = sim.world.true_tilt_deg()
        assert np.hypot(truth[0] - target[0], truth[1] - target[1]) < 0.02, (truth, target)
    # The record's points reproduce its parameters through the command line's calibration code.
    csv = client.get(f"/records/{rec['id']}/points", headers=h)
    assert csv.status_code == 200 and csv.headers["content-type"].startswith("text/csv")
    model = client.get(f"/records/{rec['id']}/model", headers=h).json()
    assert model["method"] == method
    data, out = tmp_path / "points.csv", tmp_path / "refit.json"
    data.write_bytes(csv.content)
    assert (
        cli.main(
            [
                "calibrate",
                "--kind",
                "stage",
                "--method",
                method,
                "--input",
                str(data),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    refit = json.loads(out.read_text())
    assert {k: p["value"] for k, p in refit["parameters"].items()} == {
        k: p["value"] for k, p in model["parameters"].items()
    }
    # the MODEL.json works with `tiltlab correct`
    (tmp_path / "model.json").write_text(json.dumps(model))
    assert (
        cli.main(
            [
                "correct",
                "--model",
                str(tmp_path / "model.json"),
                "--input",
                str(data),
                "--out",
                str(tmp_path / "corrected.csv"),
            ]
        )
        == 0
    )
