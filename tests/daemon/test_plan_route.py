"""The plan an adaptive job follows is the one `tiltlab plan` prints for the same bench: the same
route (its first point the spread point nearest where the stage stands, the others on a short tour,
the validation points on the way) stop for stop, and an expected bench time that a simulated job's
measured bench time bears out (the fit points' and the validation points' together)."""

from __future__ import annotations

import pytest

from service.scenarios.model import load_scenario
from service.scenarios.plan import design_floor, plan_for_scenario
from tests.helpers.daemon import admin_headers, job_from, make_client

TARGET_DEG = 0.0006
N_VALIDATION = 4
BODY = {
    "procedure": "stage-grid",
    "method": "kinematic",
    "design": "adaptive",
    "target_expanded_uncertainty_deg": TARGET_DEG,
    "grid": {"x_deg": [-12.0, 12.0], "y_deg": [-12.0, 12.0], "n_x": 9, "n_y": 9},
    "samples_per_point": 10,
    "validation": {"n_points": N_VALIDATION},
}
STANDS_AT = (0.0, 0.0)


@pytest.fixture(scope="module")
def job_and_points(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("plan-route")
    with make_client(tmp, bench_scenario="seed000") as client:
        h = admin_headers(tmp)
        job, record = job_from(client, h, BODY, STANDS_AT)
        assert job["state"] == "succeeded", job["error"]
        meas = client.app.state.bench.device_ids["measurement_sensor"]
        points = client.app.state.store.points.settled_points(job["id"], meas)
        yield job, record, points


def test_the_job_measures_the_route_the_offline_plan_prints(job_and_points):
    _, record, points = job_and_points
    offline = plan_for_scenario(load_scenario("seed000"), TARGET_DEG, STANDS_AT, N_VALIDATION, 10)
    in_time = sorted(points, key=lambda point: point.t_start_s)
    assert [point.point >= len(offline.points) for point in in_time] == [
        stop.validating for stop in offline.route
    ]
    # the commanded tilts, to the stages' pulse (some 0.0003 deg)
    assert [(point.cmd_x_deg, point.cmd_y_deg) for point in in_time] == [
        pytest.approx(stop.point, abs=0.001) for stop in offline.route
    ]
    # and the record's plan lists the fit points in that order
    plan = record["validation"]["plan"][0]
    assert [tuple(point) for point in plan["points"]] == offline.points


def test_the_expected_bench_time_is_borne_out(job_and_points):
    job, record, _ = job_and_points
    actual = job["bench_seconds"]["total"]
    rounds = record["validation"]["plan"]
    plan = rounds[0]
    expected = plan["expected_bench_seconds"] + plan["expected_validation_bench_seconds"]
    offline = plan_for_scenario(load_scenario("seed000"), TARGET_DEG, STANDS_AT, N_VALIDATION, 10)
    offline_expected = offline.bench_seconds + offline.validation_bench_seconds
    print(
        f"\nbench s: the job took {actual:.0f}, its plan expected {expected:.0f}, the offline plan "
        f"{offline_expected:.0f}"
    )
    # the validation points' part is of their share: 4 stands of 10 readings against 16 of more
    assert 0 < plan["expected_validation_bench_seconds"] < 0.3 * plan["expected_bench_seconds"]
    if len(rounds) == 1:
        # measured on this bench (docs/calibration-stage.md): the offline plan 9-15 % above the
        # job's bench time (it reckons settling from the scenario's transient with a margin); the
        # job's plan 13-33 % above over 17 jobs, most within 13-22 %: it reckons every stand's
        # settling from its first point's, which also waits for the request's settle rule and
        # then for three of its windows of readings (the noise not yet known): after a move of
        # 3 deg to that point it did not reckon short, and a first stand that happened to settle
        # slowly made it reckon long (on a slow sensor, after a short first move, it reckons
        # short: docs/calibration-stage.md)
        assert actual <= expected <= 1.5 * actual
        assert offline_expected == pytest.approx(actual, rel=0.2)
    else:
        # a top-up pass (about one job in ten) reads every point again: more than the plan
        assert actual > expected


def test_no_job_beats_the_design_floor(job_and_points):
    """The floor (every stand settled only until the move's transient is within one reading's noise,
    readings exactly at the target) is below what the job took and what either plan expects, and
    each of its parts is below the job's."""
    job, record, _ = job_and_points
    floor = design_floor(load_scenario("seed000"), TARGET_DEG, N_VALIDATION, 10)
    took = job["bench_seconds"]
    offline = plan_for_scenario(load_scenario("seed000"), TARGET_DEG, STANDS_AT, N_VALIDATION, 10)
    plan = record["validation"]["plan"][0]
    print(
        f"\nbench s: the floor {floor.total:.0f} (moving {floor.moving:.0f}, settling "
        f"{floor.settling:.0f}, reading {floor.reading:.0f}); the job {took['total']:.0f} (moving "
        f"{took['moving']:.0f}, settling {took['settling']:.0f}, reading {took['reading']:.0f})"
    )
    assert floor.settling < took["settling"]
    assert floor.reading < took["reading"]
    assert floor.total < took["total"]
    assert floor.total < offline.bench_seconds + offline.validation_bench_seconds
    assert floor.total < plan["expected_bench_seconds"] + plan["expected_validation_bench_seconds"]
