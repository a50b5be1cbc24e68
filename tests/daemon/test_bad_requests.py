"""Bad requests get the contract's status and a problem naming the field, and change nothing in the
database."""

from __future__ import annotations

import sqlalchemy as sa

from tests.helpers.daemon import wait_job

GRID = {"x_deg": [-1.0, 1.0], "y_deg": [-1.0, 1.0], "n_x": 3, "n_y": 3}


def _counts(client) -> dict[str, int]:
    with client.app.state.engine.connect() as c:
        return {
            t: c.execute(sa.text(f"SELECT count(*) FROM {t}")).scalar()
            for t in (
                "calibration_jobs",
                "settled_points",
                "samples",
                "calibration_records",
                "idempotency_keys",
            )
        }


def _problem(r, status, field_word):
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    body = r.json()
    assert body["status"] == status and body["title"] and field_word in body["detail"], body
    return body


def test_bad_calibration_requests_change_nothing(daemon):
    client, h = daemon
    before = _counts(client)
    ok = {"procedure": "stage-grid", "method": "kinematic", "grid": GRID}
    _problem(client.post("/calibrations", headers=h, json={**ok, "bench": "nope"}), 404, "bench")
    _problem(
        client.post("/calibrations", headers=h, json={**ok, "grid": {"x_deg": [-1, 1]}}),
        422,
        "grid",
    )
    _problem(
        client.post("/calibrations", headers=h, json={**ok, "grid": {**GRID, "x_deg": [-30, 1]}}),
        422,
        "grid.x_deg",
    )
    _problem(
        client.post("/calibrations", headers=h, json={**ok, "grid": {"points": [[0, 0], [1, 1]]}}),
        422,
        "grid",
    )
    # angles (the scale and rotation procedures' points) for a stage grid: refused, not a 500
    for angles in ({"angles_deg": [-1.0, 0.0, 1.0]}, {"range_deg": [-1.0, 1.0], "n": 5}):
        body = _problem(
            client.post("/calibrations", headers=h, json={**ok, "grid": angles}), 422, "stage grid"
        )
        assert body["field"] == "grid", body
    _problem(client.post("/calibrations", headers=h, json={**ok, "method": "magic"}), 422, "method")
    _problem(
        client.post("/calibrations", headers=h, json={**ok, "samples_per_point": 0}),
        422,
        "samples_per_point",
    )
    _problem(
        client.post("/calibrations", headers=h, json={**ok, "procedure": "guess"}), 422, "procedure"
    )
    _problem(client.post("/calibrations", json=ok), 401, "token")
    _problem(
        client.post("/calibrations", headers={"Authorization": "Bearer tl_wrong"}, json=ok),
        401,
        "token",
    )
    assert _counts(client) == before


def test_scopes_busy_bench_and_idempotency(daemon):
    client, h = daemon
    store = client.app.state.store
    _, reader = store.tokens.create_token("viewer", "read", actor="test")
    rh = {"Authorization": f"Bearer {reader}"}
    assert client.get("/tilt", headers=rh).status_code == 200
    before = _counts(client)
    body = {
        "procedure": "stage-grid",
        "method": "kinematic",
        "grid": GRID,
        "samples_per_point": 4,
        "validation": {"n_points": 1},
    }
    _problem(client.post("/calibrations", headers=rh, json=body), 403, "operate")
    _problem(client.post("/stage/move", headers=rh, json={"x_deg": 1, "y_deg": 1}), 403, "operate")
    assert _counts(client) == before
    r1 = client.post("/calibrations", headers={**h, "Idempotency-Key": "abc"}, json=body)
    assert r1.status_code == 202, r1.text
    r2 = client.post("/calibrations", headers={**h, "Idempotency-Key": "abc"}, json=body)
    assert r2.status_code == 200 and r2.json()["id"] == r1.json()["id"]
    mid = _counts(client)
    _problem(
        client.post(
            "/calibrations",
            headers={**h, "Idempotency-Key": "abc"},
            json={**body, "method": "homography"},
        ),
        422,
        "Idempotency-Key",
    )
    _problem(client.post("/calibrations", headers=h, json=body), 409, "held by job")
    _problem(client.post("/stage/level", headers=h, json={"x_deg": 0, "y_deg": 0}), 409, "")
    _problem(
        client.post("/stage/move", headers=h, json={"x_deg": 0, "y_deg": 0}), 409, "held by job"
    )
    assert _counts(client)["calibration_jobs"] == mid["calibration_jobs"]
    job = wait_job(client, r1.json()["id"], h)
    assert job["state"] == "succeeded", job
    listed = client.get("/calibrations?state=succeeded&limit=1", headers=h).json()
    assert [j["id"] for j in listed["jobs"]] == [job["id"]]
    # levelling: a target beyond the reach is refused before moving
    client.post(f"/records/{job['record']['id']}/activate", headers=h)
    pose = client.app.state.bench.sim.world.pose_deg
    _problem(client.post("/stage/level", headers=h, json={"x_deg": 40, "y_deg": 0}), 422, "x_deg")
    assert client.app.state.bench.sim.world.pose_deg == pose
    _problem(client.post("/stage/move", headers=h, json={"x_deg": 40, "y_deg": 0}), 422, "x_deg")
    _problem(client.get("/calibrations/999", headers=h), 404, "999")
    _problem(client.get("/records/999", headers=h), 404, "999")
    _problem(client.get("/devices?bench=nope", headers=h), 404, "bench")


def test_simultaneous_requests_make_one_job(daemon):
    """Four clients ask for a job on the same bench at once: one job is made, the others are told
    the bench is busy (the bench is taken before the job row is written)."""
    from concurrent.futures import ThreadPoolExecutor

    client, h = daemon
    before = _counts(client)
    ok = {"procedure": "stage-grid", "method": "kinematic", "grid": GRID, "samples_per_point": 4}
    with ThreadPoolExecutor(4) as pool:
        answers = list(
            pool.map(lambda _: client.post("/calibrations", headers=h, json=ok), range(4))
        )
    assert sorted(r.status_code for r in answers) == [202, 409, 409, 409], [r.text for r in answers]
    for r in answers:
        if r.status_code == 409:
            _problem(r, 409, "held by")
    assert _counts(client)["calibration_jobs"] == before["calibration_jobs"] + 1
    job_id = next(r.json()["id"] for r in answers if r.status_code == 202)
    assert wait_job(client, job_id, h)["state"] == "succeeded"
