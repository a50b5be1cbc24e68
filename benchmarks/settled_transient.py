"""How much of the settling transient each stage-grid job leaves in the points it stores.

    python benchmarks/settled_transient.py
    python benchmarks/settled_transient.py --scenarios seed000-slow --speed 10

A job's points are means of readings taken once its settle rule said the table had settled. What
is left of the transient then biases the point's mean. No bench shows that bias (a reading is the
table plus the transient plus noise); the simulator knows it, and keeps it while this benchmark
asks (`World.transient_log`). On each scenario (seed000 with the presets' 0.3 s sensor, and
seed000-slow with a 1.5 s one, as in benchmarks/bench_time.py) a daemon runs, over +-12 deg
(kinematic, 8 validation points):

* today's fixed 9 x 9 job with the default settle rule (0.5 s windows within 0.002 deg);
* the same job with a stricter rule: 2 s windows within 0.0005 deg (half a reading's noise);
* the adaptive job, its target the U the first job predicted (its settling: the statistical test).

Prints per job: bench seconds (total, settling), points, readings a point, and the transient left in
the points' means as an angle of each stage: rms, the largest, and the share of points where it
exceeds the standard error of the point's mean (reading noise / sqrt(readings)).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_time import BASE_JOB, daemon_on, run_job  # noqa: E402

from service.reproduce.settled_transient import transient_in_points  # noqa: E402
from service.scenarios import parse_scenario  # noqa: E402
from service.scenarios.model import StageScenario, scenario_data  # noqa: E402
from service.scenarios.plan import scenario_noise  # noqa: E402

STRICT_SETTLE = {"tolerance_deg": 0.0005, "window_s": 2.0, "timeout_s": 120.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed", type=float, default=10.0, help="simulation speed (default 10)")
    ap.add_argument("--scenarios", nargs="+", default=["seed000", "seed000-slow"])
    args = ap.parse_args()
    print(
        "| scenario / job | state | bench s | settling | points | readings a point | "
        "transient rms x / y deg | largest x / y deg | points above the mean's standard error |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for name in args.scenarios:
        with daemon_on(name, args.speed) as (client, h, path):
            scenario = parse_scenario(*scenario_data(path))
            assert isinstance(scenario, StageScenario), name
            noise = scenario_noise(scenario)
            world = client.app.state.bench.sim.world  # type: ignore[attr-defined]
            base = BASE_JOB
            strict = {**base, "settle": STRICT_SETTLE}
            target = None
            for label, body in (
                ("fixed 9 x 9, default settle rule", base),
                ("fixed 9 x 9, 2 s windows within 0.0005 deg", strict),
                ("adaptive", None),
            ):
                if body is None:
                    if target is None:
                        continue
                    label = f"adaptive, target {target:.5f}"
                    body = {
                        **base,
                        "design": "adaptive",
                        "target_expanded_uncertainty_deg": round(float(target), 6),
                    }
                log: list[Any] = []
                world.transient_log = log
                res = run_job(client, h, body)
                world.transient_log = None
                if target is None:
                    target = (res.get("validation") or {}).get("predicted_expanded_uncertainty_deg")
                bias, counts = transient_in_points(client.app, res["id"], log)
                standard_error = noise.ref_sigma_deg / np.sqrt(counts)
                above = (np.abs(bias).max(axis=1) > standard_error).mean()
                rms = np.sqrt((bias**2).mean(axis=0))
                largest = np.abs(bias).max(axis=0)
                b = res["bench_seconds"] or {}
                print(
                    f"| {name}: {label} | {res['state']} | {b.get('total', 0):.0f} | "
                    f"{b.get('settling', 0):.0f} | {len(counts)} | {counts.mean():.0f} | "
                    f"{rms[0]:.1e} / {rms[1]:.1e} | {largest[0]:.1e} / {largest[1]:.1e} | "
                    f"{above * 100:.0f} % |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
