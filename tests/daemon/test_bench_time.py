"""Every job reports the bench time it spent, by activity, in bench seconds: the parts add up to the
total, the job and its record state the same figures, and a faster simulation does not change
them."""

from __future__ import annotations

import pytest

from tests.helpers.daemon import admin_headers, make_client, wait_job

GRID = {"x_deg": [-3.0, 3.0], "y_deg": [-3.0, 3.0], "n_x": 3, "n_y": 3}
PARTS = ("moving", "settling", "reading")


def _run(tmp_path, speed: float) -> tuple[dict, dict]:
    with make_client(tmp_path, sim_speed=speed) as client:
        h = admin_headers(tmp_path)
        r = client.post(
            "/calibrations",
            headers=h,
            json={
                "procedure": "stage-grid",
                "method": "kinematic",
                "grid": GRID,
                "samples_per_point": 5,
                "validation": {"n_points": 2},
            },
        )
        assert r.status_code == 202, r.text
        job = wait_job(client, r.json()["id"], h)
        assert job["state"] == "succeeded", job
        record = client.get(f"/records/{job['record']['id']}", headers=h).json()
        return job, record


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return {speed: _run(tmp_path_factory.mktemp(f"speed{speed:g}"), speed) for speed in (4.0, 12.0)}


def test_bench_seconds_add_up_and_the_record_keeps_them(runs):
    for job, record in runs.values():
        b = job["bench_seconds"]
        assert b["total"] == pytest.approx(sum(b[p] for p in PARTS), abs=0.01)
        assert all(b[p] > 0 for p in PARTS)
        assert record["bench_seconds"] == b
        # 11 points, each read 5 times at the sensors' output interval: at least 4 intervals of
        # reading each
        assert b["reading"] >= 11 * 4 * 0.04 * 0.9


def test_bench_seconds_do_not_change_with_the_simulation_speed(runs):
    """The same job at 4x and 12x: the total within 10 %, each part within 20 %. The bench clock
    measures them as a real bench's would. A move ends when the controller's state query found the
    axes standing (the time the query was asked), so the real-time latency of reading its answer,
    which a sped-up simulation turns into speed x more bench seconds (and more on a loaded machine),
    is not counted as moving."""
    slow, fast = runs[4.0][0]["bench_seconds"], runs[12.0][0]["bench_seconds"]
    assert fast["total"] == pytest.approx(slow["total"], rel=0.10), (slow, fast)
    for p in PARTS:
        # a part of a few seconds (reading) also moves by the sensors' 10 ms bursts, which are 0.12
        # bench s at 12x for each point's last reading: one bench second over the job's nine points
        assert fast[p] == pytest.approx(slow[p], rel=0.20, abs=1.0), (p, slow, fast)
