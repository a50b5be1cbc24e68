"""Homing a stage whose controller starts as after power-up ("not homed"), through `tiltlab serve`.

A simulated bench whose scenario says `controller_homed: false` refuses moves until homed: a move
is 409 naming the cause and the route to use; `POST /stage/home` homes both axes; a calibration job
on such a bench homes the stage itself before its first point and succeeds.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.helpers.running_service import running_service
from tests.helpers.waiting import eventually

ROOT = Path(__file__).resolve().parents[2]


def unhomed_scenario(folder: Path) -> Path:
    data = json.loads((ROOT / "service" / "scenarios" / "presets" / "seed000.json").read_text())
    data["controller_homed"] = False
    path = folder / "unhomed.json"
    path.write_text(json.dumps(data))
    return path


class Daemon:
    def __init__(self, base: str, token: str) -> None:
        self.base, self.h = base, {"Authorization": f"Bearer {token}"}

    def get(self, path: str) -> httpx.Response:
        return httpx.get(self.base + path, headers=self.h, timeout=60)

    def post(self, path: str, body: dict | None = None) -> httpx.Response:
        return httpx.post(self.base + path, headers=self.h, json=body, timeout=120)


def _wait_bench_ready(d: Daemon) -> None:
    eventually(
        lambda: d.get("/benches").json()["benches"][0]["state"] == "ready",
        timeout_s=60,
        every_s=0.2,
        what="the bench up (ready)",
    )


@pytest.fixture()
def daemon(tmp_path) -> Iterator[Daemon]:
    data = tmp_path / "data"
    data.mkdir()
    with running_service(
        data, TILTLAB_SIM_SPEED="20", TILTLAB_BENCH_SCENARIO=str(unhomed_scenario(tmp_path))
    ) as base:
        d = Daemon(base, (data / "admin.token").read_text().strip())
        _wait_bench_ready(d)
        yield d


def test_a_stage_that_is_not_homed_is_homed_by_the_route(daemon: Daemon) -> None:
    refused = daemon.post("/stage/move", {"x_deg": 1.0, "y_deg": 0.5})
    assert refused.status_code == 409, refused.text
    problem = refused.json()
    assert problem["title"] == "Stage not homed" and "POST /stage/home" in problem["detail"], (
        problem
    )

    homed = daemon.post("/stage/home", {})
    assert homed.status_code == 200, homed.text
    assert homed.json()["homed"] is True
    assert homed.json()["stage"] == {"x_deg": 0.0, "y_deg": 0.0, "moving": False}

    moved = daemon.post("/stage/move", {"x_deg": 1.0, "y_deg": 0.5})
    assert moved.status_code == 200, moved.text
    stage = moved.json()["stage"]
    assert stage["x_deg"] == pytest.approx(1.0, abs=1e-3) and stage["y_deg"] == pytest.approx(
        0.5, abs=1e-3
    )
    assert daemon.post("/stage/home", {"bench": "no-such-bench"}).status_code == 404


def test_a_job_homes_the_stage_before_its_first_point(daemon: Daemon) -> None:
    body = {
        "procedure": "stage-grid",
        "method": "coupling",
        "samples_per_point": 3,
        "validation": {"n_points": 1},
        "grid": {"x_deg": [-1, 1], "y_deg": [-1, 1], "n_x": 2, "n_y": 2},
        "settle": {"tolerance_deg": 0.005},
    }
    r = daemon.post("/calibrations", body)
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    phases = set()

    def job_seen() -> dict:
        job = daemon.get(f"/calibrations/{job_id}").json()
        phases.add(job["progress"]["phase"])
        return job

    job = eventually(
        job_seen,
        until=lambda job: job["state"] in ("succeeded", "failed", "cancelled"),
        timeout_s=240,
        every_s=0.1,
        what=f"job {job_id} ended",
    )
    assert job["state"] == "succeeded", job
    assert job["progress"]["phase"] == "done", job
    # homed for good
    assert daemon.post("/stage/move", {"x_deg": 0.2, "y_deg": 0.2}).status_code == 200


def test_a_stop_during_homing_is_a_conflict_not_a_device_fault(tmp_path) -> None:
    """`POST /stage/stop` while `POST /stage/home` runs: the homing answers 409 saying it was
    stopped (the instruments answer; nothing is wrong with them), and the stage can be homed
    afterwards."""
    import threading

    data = tmp_path / "data"
    data.mkdir()
    with running_service(
        data, TILTLAB_SIM_SPEED="1", TILTLAB_BENCH_SCENARIO=str(unhomed_scenario(tmp_path))
    ) as base:
        d = Daemon(base, (data / "admin.token").read_text().strip())
        _wait_bench_ready(d)
        assert d.post("/stage/home", {}).status_code == 200
        # far from the switches
        assert d.post("/stage/move", {"x_deg": 8.0, "y_deg": -8.0}).status_code == 200
        answers: list[httpx.Response] = []
        homing = threading.Thread(target=lambda: answers.append(d.post("/stage/home", {})))
        homing.start()

        def homing_holds_the_bench() -> bool:
            if d.get("/benches").json()["benches"][0].get("held_by") is not None:
                return True
            assert homing.is_alive(), "homing never held the bench: it ended"
            return False

        eventually(
            homing_holds_the_bench, timeout_s=60, every_s=0.02, what="homing holding the bench"
        )
        stopped = d.post("/stage/stop", {})
        homing.join(timeout=120)
        assert stopped.status_code == 200, stopped.text
        assert answers and answers[0].status_code == 409, (
            answers[0].text if answers else "no answer"
        )
        problem = answers[0].json()
        assert problem["title"] == "Motion stopped" and "POST /stage/stop" in problem["detail"], (
            problem
        )
        homed = d.post("/stage/home", {})
        assert homed.status_code == 200, homed.text
