"""Counts and ids are integers, and JSON Schema's integer includes a number with no fractional part:
`18.0` is accepted wherever `18` is (in bodies and in queries), `18.5` is refused naming the field.
A client that writes every number as a float (many JSON libraries, spreadsheets) is not refused."""

from __future__ import annotations

from tests.helpers.daemon import admin_headers, make_client

GRID = {"x_deg": [-2.0, 2.0], "y_deg": [-2.0, 2.0], "n_x": 3, "n_y": 3}


def test_integer_valued_floats_are_integers_and_fractions_are_refused(tmp_path) -> None:
    with make_client(tmp_path) as client:
        h = admin_headers(tmp_path)
        body = {
            "procedure": "stage-grid",
            "method": "kinematic",
            "grid": {**GRID, "n_x": 3.0, "n_y": 3.0},
            "samples_per_point": 5.0,
            "validation": {"n_points": 0.0},
        }
        fraction = {**body, "grid": {**GRID, "n_x": 3.5}}
        refused = client.post("/calibrations", headers=h, json=fraction)
        assert refused.status_code == 422 and refused.json()["field"] == "grid.n_x", refused.text
        made = client.post("/calibrations", headers=h, json=body)
        assert made.status_code == 202, made.text
        job = made.json()
        assert job["progress"]["points_total"] == 9, job  # 3 x 3, counted as integers
        # queries: a page size
        assert client.get("/records", headers=h, params={"limit": "18.0"}).status_code == 200
        listed = client.get("/calibrations", headers=h, params={"limit": "18.0"})
        assert listed.status_code == 200 and listed.json()["jobs"][0]["id"] == job["id"]
        half = client.get("/records", headers=h, params={"limit": "18.5"})
        assert half.status_code == 422 and "limit" in half.text, half.text
