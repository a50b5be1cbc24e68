"""GET /records/{id}/residuals: per-point residuals before and after correction, as `tiltlab
correct` computes them."""

from __future__ import annotations

import csv
import io
import json

import numpy as np

from service import cli
from tests.helpers.daemon import wait_job

GRID = {"x_deg": [-1.5, 1.5], "y_deg": [-1.5, 1.5], "n_x": 3, "n_y": 3}


def test_residuals_before_and_after_correction(daemon, tmp_path):
    client, h = daemon
    r = client.post(
        "/calibrations",
        headers=h,
        json={
            "procedure": "stage-grid",
            "method": "kinematic",
            "grid": GRID,
            "samples_per_point": 5,
            "validation": {"n_points": 2},
            "settle": {"tolerance_deg": 0.005, "window_s": 0.5, "timeout_s": 60},
        },
    )
    assert r.status_code == 202, r.text
    job = wait_job(client, r.json()["id"], h)
    assert job["state"] == "succeeded", job
    rec_id = job["record"]["id"]

    res = client.get(f"/records/{rec_id}/residuals", headers=h)
    assert res.status_code == 200, res.text
    body = res.json()
    pts = body["points"]
    assert body["record_id"] == rec_id and body["n_fit"] == 9
    assert [p["role"] for p in pts].count("fit") == 9 and [p["role"] for p in pts].count(
        "validation"
    ) == 2

    # "before" is the raw measurement minus the reference, point by point, from the record's points
    # CSV
    rows = list(
        csv.DictReader(io.StringIO(client.get(f"/records/{rec_id}/points", headers=h).text))
    )
    by_point = {int(p["point"]): p for p in pts}
    for row in rows:
        p = by_point[int(row["point"])]
        assert p["before_x_deg"] == float(row["meas_x_deg"]) - float(row["ref_x_deg"])
        assert p["before_y_deg"] == float(row["meas_y_deg"]) - float(row["ref_y_deg"])

    # "after" is what `tiltlab correct` gives with the record's MODEL.json, minus the reference
    (tmp_path / "model.json").write_text(
        json.dumps(client.get(f"/records/{rec_id}/model", headers=h).json())
    )
    (tmp_path / "points.csv").write_text(client.get(f"/records/{rec_id}/points", headers=h).text)
    assert (
        cli.main(
            [
                "correct",
                "--model",
                str(tmp_path / "model.json"),
                "--input",
                str(tmp_path / "points.csv"),
                "--out",
                str(tmp_path / "corrected.csv"),
            ]
        )
        == 0
    )
    for row in csv.DictReader(open(tmp_path / "corrected.csv")):
        p = by_point[int(row["point"])]
        # the CSV carries 7 decimals
        assert np.isclose(
            p["after_x_deg"], float(row["tilt_x_deg"]) - float(row["ref_x_deg"]), atol=1e-6
        )
        # the CSV carries 7 decimals
        assert np.isclose(
            p["after_y_deg"], float(row["tilt_y_deg"]) - float(row["ref_y_deg"]), atol=1e-6
        )

    # correction shrinks the residuals: the mounting error is in "before", not in "after"
    assert body["rms_after_deg"] < body["rms_before_deg"]
    assert client.get("/records/999999/residuals", headers=h).status_code == 404
    assert client.get(f"/records/{rec_id}/residuals").status_code == 401
