"""`GET /tilt?average_s=T`: the mean of the corrected readings since the later of T seconds ago and
the end of the stage's last move, with the uncertainty of that mean; refused outside 0 < T <= 600,
null while fewer than two readings are had."""

from __future__ import annotations

import numpy as np

from tests.helpers.daemon import admin_headers, calibrate_and_activate, make_client
from tests.helpers.waiting import eventually

GRID = {"x_deg": [-2.0, 2.0], "y_deg": [-2.0, 2.0], "n_x": 3, "n_y": 3}


def _after(bench, bench_s: float) -> None:
    """Wait until the bench clock has passed `bench_s`."""
    eventually(
        lambda: bench.clock.monotonic() > bench_s, timeout_s=60, what=f"bench time {bench_s:.1f} s"
    )


def test_the_average_of_the_settled_stand_states_the_uncertainty_of_the_mean(
    tmp_path,
):
    with make_client(tmp_path) as client:
        h = admin_headers(tmp_path)
        calibrate_and_activate(
            client,
            h,
            {
                "procedure": "stage-grid",
                "method": "kinematic",
                "grid": GRID,
                "samples_per_point": 5,
                "validation": {"n_points": 0},
            },
        )
        bench = client.app.state.bench
        for bad in (0, -1, 601, "soon"):
            r = client.get("/tilt", headers=h, params={"average_s": bad})
            assert r.status_code == 422 and "average_s" in r.text, (bad, r.text)

        assert (
            client.post("/stage/move", headers=h, json={"x_deg": 1.0, "y_deg": -0.5}).status_code
            == 200
        )
        stood = bench.pose.still_since_bench_s
        assert stood is not None and not bench.pose.moving
        # the settling transient has died out (the preset's), then readings at rest
        _after(bench, stood + 6.0)
        single = client.get("/tilt", headers=h).json()["table_tilt"]
        assert single["n_readings"] is None and single["window_s"] is None  # one reading: no window

        # a window reaching back past the move holds only the readings since they settled after it,
        # and says so (the table's transient is not averaged)
        long = client.get("/tilt", headers=h, params={"average_s": 600}).json()
        table = long["table_tilt"]
        assert table is not None, long["note"]
        assert (
            2.0 < table["window_s"] < 600 and "settled after the stage's last move" in long["note"]
        ), long
        assert table["window_s"] < bench.clock.monotonic() - stood, table
        # every reading since they settled: about 25 readings a second of the window (the sensor's
        # output rate)
        assert 20 * table["window_s"] <= table["n_readings"] <= 30 * table["window_s"], table

        short = client.get("/tilt", headers=h, params={"average_s": 2}).json()["table_tilt"]
        # readings are stamped when they are parsed: on a loaded machine a bench sped up 20 times
        # (2 bench seconds are 0.1 s of the machine's) delivers them in bursts, so a short window
        # holds about its share, give or take a burst; the long window above holds the rate
        assert 1.5 <= short["window_s"] <= 2.0 and 10 <= short["n_readings"] <= 150, short
        for axis in ("x", "y"):
            u, U = (
                short[f"standard_uncertainty_{axis}_deg"],
                short[f"expanded_uncertainty_{axis}_deg"],
            )
            assert abs(U - short[f"coverage_factor_{axis}"] * u) < 1e-12
            # the deprecated alias is the expanded uncertainty here too
            assert short[f"u_{axis}_deg"] == U
            # the mean of many readings at rest is known better than one reading
            assert U < single[f"expanded_uncertainty_{axis}_deg"], (short, single)
            # (that correlated readings, such as a settling table's, are worth fewer independent
            # ones and the U of their mean says so is tested on known series in
            # tests/calibration/test_mean_type_a.py: here, on a bench sped up 20 times, how much of
            # the transient a window holds depends on how late the request comes)
            assert (
                table[f"expanded_uncertainty_{axis}_deg"]
                < single[f"expanded_uncertainty_{axis}_deg"]
            ), (table, single)
            # the mean agrees with one reading within three of their standard uncertainties combined
            # (a 95 % bound would fail one run in twenty on two axes)
            both = np.hypot(u, single[f"standard_uncertainty_{axis}_deg"])
            assert abs(short[f"{axis}_deg"] - single[f"{axis}_deg"]) <= 3 * both, (short, single)
        assert short["coverage_probability"] == 0.95

        # right after a move there is nothing to average yet (the readings have not settled), or
        # very little
        assert (
            client.post("/stage/move", headers=h, json={"x_deg": -1.0, "y_deg": 0.5}).status_code
            == 200
        )
        fresh = client.get("/tilt", headers=h, params={"average_s": 30}).json()
        if fresh["table_tilt"] is None:
            assert (
                "not yet settled" in fresh["note"]
                or "an average needs two or more" in fresh["note"]
            ), fresh
        else:
            assert (
                fresh["table_tilt"]["window_s"] < 30
                and "settled after the stage's last move" in fresh["note"]
            ), fresh
