"""`tiltlab plan` as a lab engineer runs it: the adaptive plan for a bench description and a target,
without a bench; a target the bench cannot reach exits 2 naming the floor."""

import json
import subprocess
import sys

import pytest

from service.calibration.adaptive_design import (
    PLAN_MARGINS,
    BenchNoise,
    Design,
    lattice,
    top_up_probability,
)
from service.scenarios.model import load_scenario
from service.scenarios.plan import scenario_noise


def tiltlab(*args):
    return subprocess.run([sys.executable, "-m", "service", *args], capture_output=True, text=True)


def test_plan_prints_points_readings_bench_time_and_predicted_u():
    r = tiltlab("plan", "--scenario", "seed000", "--target", "0.0006", "--json")
    assert r.returncode == 0, r.stderr
    plan = json.loads(r.stdout)
    # it aims below the target by the margin whose readings and top-up risk cost least
    predicted = plan["predicted_expanded_uncertainty_deg"]
    assert predicted <= plan["aimed_expanded_uncertainty_deg"] * (1 + 1e-9)
    assert min(PLAN_MARGINS) * 0.0006 <= plan["aimed_expanded_uncertainty_deg"] < 0.0006
    assert plan["top_up_probability"] == top_up_probability(predicted / 0.0006, len(plan["points"]))
    assert len(plan["points"]) >= 16 and len(plan["readings"]) == len(plan["points"])
    assert plan["expected_bench_seconds"] > 0
    # the prediction is the planner's formula on the scenario's noise: recomputed here from the
    # chosen points
    sc = load_scenario("seed000")
    noise = scenario_noise(sc)
    cand = lattice((-12, 12), (-12, 12), 9, 9)
    design = Design(cand, lattice((-12, 12), (-12, 12), 13, 13), noise)
    counts = [0.0] * 81
    for (x, y), n in zip(plan["points"], plan["readings"]):
        counts[int(round((y + 12) / 3)) * 9 + int(round((x + 12) / 3))] = n
    import numpy as np

    assert design.expanded_u(np.array(counts)) == plan["predicted_expanded_uncertainty_deg"]
    # a tighter target asks for more readings or more points
    tight = json.loads(
        tiltlab("plan", "--scenario", "seed000", "--target", "0.0003", "--json").stdout
    )
    assert sum(tight["readings"]) > sum(plan["readings"])
    text = tiltlab("plan", "--scenario", "seed000", "--target", "0.0006")
    assert (
        text.returncode == 0 and "expected bench time" in text.stdout and "readings" in text.stdout
    )


def test_unreachable_target_exits_2_naming_the_floor():
    r = tiltlab("plan", "--scenario", "seed000", "--target", "0.00001")
    assert r.returncode == 2
    assert "cannot be reached" in r.stderr and "8.165e-05 deg" in r.stderr
    r = tiltlab("plan", "--scenario", "seed003", "--target", "0.001")
    assert r.returncode == 2 and "stage" in r.stderr


def test_bench_noise_of_the_scenario():
    n = scenario_noise(load_scenario("seed000"))
    assert isinstance(n, BenchNoise) and 0.001 < n.meas_sigma_deg < 0.00101


def test_plan_prints_the_jobs_route_from_where_the_stage_stands():
    r = tiltlab(
        "plan", "--scenario", "seed000", "--target", "0.0006", "--from", "11", "-10",
        "--validation-points", "6", "--samples-per-point", "12", "--json",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    plan = json.loads(r.stdout)
    route = plan["route"]
    # the spread point nearest (11, -10) first; every fit point once, in the plan's order
    assert (route[0]["x_deg"], route[0]["y_deg"], route[0]["validation"]) == (12.0, -12.0, False)
    fit = [stop for stop in route if not stop["validation"]]
    assert [[stop["x_deg"], stop["y_deg"]] for stop in fit] == plan["points"]
    assert [stop["readings"] for stop in fit] == plan["readings"]
    validation = [stop for stop in route if stop["validation"]]
    assert len(validation) == 6 and all(stop["readings"] == 12 for stop in validation)
    assert all(-12 <= stop["x_deg"] <= 12 and -12 <= stop["y_deg"] <= 12 for stop in validation)
    assert 0 < plan["expected_validation_bench_seconds"] < plan["expected_bench_seconds"]
    text = tiltlab("plan", "--scenario", "seed000", "--target", "0.0006").stdout
    assert "4 validation points on the way" in text and text.count("validation\n") == 4


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--validation-points", "-1"], "--validation-points -1"),
        (["--samples-per-point", "0"], "--samples-per-point 0"),
        (["--from", "nan", "0"], "--from"),
    ],
)
def test_bad_route_options_exit_2_naming_them(args, named):
    r = tiltlab("plan", "--scenario", "seed000", "--target", "0.0006", *args)
    assert r.returncode == 2 and named in r.stderr, r.stderr
