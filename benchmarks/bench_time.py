"""Bench time of a stage calibration: seed 000's procedure, today's fixed 9 x 9 job and the adaptive
job.

    python benchmarks/bench_time.py
    python benchmarks/bench_time.py --speed 20 --scenarios seed000

On each scenario (seed000 and seed000-worm, whose presets state settling, and a slow-sensor variant
of seed000 with a 1.5 s time constant, as high-resolution addressable sensors have), a daemon on the
simulated bench runs three stage-grid jobs over +-12 deg (kinematic, 8 validation points each):

* seed 000's procedure: the 9 x 9 grid at 3 deg, 20 s of settling per point (the settle rule with
  0.5 s ... 10 s windows: at least 20 s), 10 readings a point;
* today's fixed 9 x 9 job: the default settle rule, 10 readings a point;
* the adaptive job, its target the predicted U today's 9 x 9 job reached on that bench.

Prints per job: bench seconds (total, moving, settling, reading), the predicted expanded U of the
correction over the range, the validation RMS, the validated expanded U and the validated coverage;
then the adaptive job's bench time as a fraction of today's 9 x 9 job's. Bench seconds are the
simulated clock's (docs/api.md, "Bench time").

One adaptive job's bench time depends on its draws: whether its fit predicts more than the target
and reads every point again (a top-up pass). `--adaptive-runs N` runs it N times at the same target
and prints, per bench, the median and range of its fraction of the fixed job's bench time, how many
runs came within 0.35 x, how many needed a top-up pass, how many of their validation components
lay within their expanded uncertainty, and what the plan expected over what the job took. Each
bench's summary also states the adaptive design's floor there (service.scenarios.plan.design_floor):
the least bench time any adaptive job could take on it, with every stand settled only until its
transient is within one reading's noise and its readings exactly at the target; and the floor of a
job whose point means carry at most half their standard error of the transient
(MEAN_SHARE: a slow sensor's remnant at one reading's noise biases a long mean by several).
`--no-seed000-procedure` leaves out the longest job (some 2,000 bench s a bench) when only the other
two are wanted.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import tempfile
import time
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.config import Settings
from service.scenarios import load_scenario
from service.scenarios.model import scenario_data
from service.scenarios.plan import design_floor

GRID = {"x_deg": [-12.0, 12.0], "y_deg": [-12.0, 12.0], "n_x": 9, "n_y": 9}
# the floor's second figure: the transient in each point's mean within this share of the mean's
# standard error (a bias of half of it alone takes a 95 % interval on the mean to some 92 %)
MEAN_SHARE = 0.5
SLOW = {
    "sensor_time_constant_s": 1.5,
    "ringing_amplitude_deg_per_deg": 0.002,
    "ringing_frequency_hz": 2.5,
    "ringing_decay_s": 1.0,
}


def scenario_file(name: str, folder: Path) -> str:
    if name != "seed000-slow":
        return name
    data, _ = scenario_data("seed000")
    data = {
        **data,
        "name": "seed000-slow",
        "description": "seed000 with a 1.5 s sensor time constant",
        "effects": {**data["effects"], "settling": SLOW},
    }
    path = folder / "seed000-slow.json"
    path.write_text(json.dumps(data))
    return str(path)


# every job here: kinematic over +-12 deg, 10 readings a point, 8 validation points
READINGS, VALIDATION_POINTS = 10, 8
BASE_JOB: dict[str, Any] = {
    "procedure": "stage-grid",
    "method": "kinematic",
    "grid": GRID,
    "samples_per_point": READINGS,
    "validation": {"n_points": VALIDATION_POINTS},
}


@contextlib.contextmanager
def daemon_on(name: str, speed: float) -> Iterator[tuple[TestClient, dict[str, str], str]]:
    """An in-process daemon on the scenario `name` (a preset, or seed000-slow), sped up `speed`
    times, in a data directory of its own: its client, admin headers and the scenario's path."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        path = scenario_file(name, folder)
        settings = Settings(
            data_dir=folder, sim_speed=speed, sim_transport="loopback", bench_scenario=path
        )
        with TestClient(create_app(settings)) as client:
            yield (
                client,
                {"Authorization": "Bearer " + (folder / "admin.token").read_text().strip()},
                path,
            )


def run_job(client: TestClient, h: dict[str, str], body: dict[str, Any]) -> dict[str, Any]:
    r = client.post("/calibrations", headers=h, json=body)
    r.raise_for_status()
    job_id = r.json()["id"]
    while True:
        job = client.get(f"/calibrations/{job_id}", headers=h).json()
        if job["state"] in ("succeeded", "failed", "cancelled"):
            break
        time.sleep(0.5)
    out = {
        "id": job_id,
        "state": job["state"],
        "error": job["error"],
        "bench_seconds": job["bench_seconds"],
    }
    if job["record"]:
        out["validation"] = client.get(f"/records/{job['record']['id']}", headers=h).json()[
            "validation"
        ]
    return out


def row(label: str, res: dict[str, Any]) -> str:
    b = res["bench_seconds"] or {}
    v = res.get("validation") or {}

    def f(key: str, scale: float = 1.0, fmt: str = "{:.5f}") -> str:
        val = v.get(key)
        return fmt.format(val * scale) if isinstance(val, int | float) else "-"

    return (
        f"| {label} | {res['state']} | {b.get('total', 0):.0f} | {b.get('moving', 0):.0f} | "
        f"{b.get('settling', 0):.0f} | "
        f"{b.get('reading', 0):.0f} | {f('predicted_expanded_uncertainty_deg')} | {f('rms_deg')} | "
        f"{f('validated_expanded_uncertainty_deg')} | {f('validated_coverage', 100, '{:.0f} %')} |"
    )


def top_up_passes(res: dict[str, Any]) -> int:
    """How many times an adaptive job read its points again (its plan's top-up rounds)."""
    plan = (res.get("validation") or {}).get("plan") or []
    return sum(1 for step in plan if "top_up" in step)


def plan_expected_share(res: dict[str, Any]) -> float | None:
    """What an adaptive job's plan expected (fit and validation points) over the bench time it
    took."""
    plan = (res.get("validation") or {}).get("plan") or []
    if not plan or "expected_validation_bench_seconds" not in plan[0]:
        return None
    expected = plan[0]["expected_bench_seconds"] + plan[0]["expected_validation_bench_seconds"]
    return float(expected / res["bench_seconds"]["total"])


def validation_within(runs: list[dict[str, Any]]) -> tuple[int, int]:
    """How many of the runs' validation components lay within their expanded uncertainty, of how
    many."""
    within = components = 0
    for res in runs:
        validation = res.get("validation") or {}
        if validation.get("validated_components"):
            n = int(validation["validated_components"])
            within += round(float(validation["validated_coverage"]) * n)
            components += n
    return within, components


def summary(name: str, r: dict[str, Any]) -> str:
    """The adaptive job's bench time as a fraction of the fixed job's (each run's, or their median
    and range), and seed 000's procedure's."""
    fixed = r["fixed"]["bench_seconds"]
    if not fixed:
        return f"{name}: the fixed 9 x 9 job did not finish ({r['fixed']['state']})"
    done = [res for res in r["adaptive_runs"] if res["bench_seconds"]]
    ratios = sorted(res["bench_seconds"]["total"] / fixed["total"] for res in done)
    parts = [f"{name}:"]
    if len(ratios) == 1:
        parts.append(f"adaptive / fixed 9 x 9 bench time = {ratios[0]:.2f};")
    elif ratios:
        parts.append(
            f"adaptive / fixed 9 x 9 bench time over {len(ratios)} runs: median "
            f"{float(np.median(ratios)):.2f}, {ratios[0]:.2f}-{ratios[-1]:.2f}, "
            f"{sum(ratio <= 0.35 for ratio in ratios)} at or below 0.35, "
            f"{sum(top_up_passes(res) > 0 for res in done)} with a top-up pass;"
        )
    within, components = validation_within(done)
    if components:
        parts.append(
            f"{within} of {components} validation components ({within / components:.1%}) within "
            "their U;"
        )
    expected = sorted(filter(None, (plan_expected_share(res) for res in done)))
    if expected:
        parts.append(
            f"the plan expected {expected[0]:.2f}-{expected[-1]:.2f} x the bench time a job took;"
        )
    failed = len(r["adaptive_runs"]) - len(done)
    if failed:
        parts.append(f"{failed} adaptive run(s) without bench time;")
    floor, kept_out = r.get("floor"), r.get("floor_means")
    if floor:
        parts.append(
            f"the adaptive design's floor on this bench {floor['total']:.0f} s (moving "
            f"{floor['moving']:.0f}, settling {floor['settling']:.0f}, reading "
            f"{floor['reading']:.0f}) = {floor['total'] / fixed['total']:.2f} x the fixed job;"
        )
    if kept_out:
        parts.append(
            f"with the transient in each point's mean within {MEAN_SHARE:g} of its standard "
            f"error {kept_out['total']:.0f} s (settling {kept_out['settling']:.0f}) = "
            f"{kept_out['total'] / fixed['total']:.2f} x;"
        )
    seed = r["seed000_procedure"]["bench_seconds"]
    if seed:
        parts.append(f"seed 000 procedure / fixed = {seed['total'] / fixed['total']:.2f}")
    return " ".join(parts).rstrip(";")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--speed", type=float, default=20.0, help="simulation speed (bench time is the same at any)"
    )
    ap.add_argument("--scenarios", nargs="+", default=["seed000", "seed000-worm", "seed000-slow"])
    ap.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    ap.add_argument(
        "--adaptive-runs",
        type=int,
        default=1,
        metavar="N",
        help="run the adaptive job N times at the same target (default 1)",
    )
    ap.add_argument(
        "--no-seed000-procedure",
        action="store_true",
        help="leave out seed 000's procedure (20 s settling a point)",
    )
    args = ap.parse_args()
    if args.adaptive_runs < 1:
        ap.error(f"--adaptive-runs must be at least 1, got {args.adaptive_runs}")
    results: dict[str, Any] = {}
    print(
        "| scenario / job | state | bench s | moving | settling | reading | predicted U deg | "
        "validation RMS deg | validated U deg | validated coverage |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for name in args.scenarios:
        with daemon_on(name, args.speed) as (client, h, path):
            base = BASE_JOB
            seed000 = (
                {"state": "not run", "bench_seconds": None}
                if args.no_seed000_procedure
                else run_job(
                    client,
                    h,
                    {
                        **base,
                        "settle": {"tolerance_deg": 0.002, "window_s": 10.0, "timeout_s": 600.0},
                    },
                )
            )
            if not args.no_seed000_procedure:
                print(row(f"{name}: seed 000 procedure (20 s settling)", seed000), flush=True)
            fixed = run_job(client, h, base)
            print(row(f"{name}: fixed 9 x 9 job", fixed), flush=True)
            target = (fixed.get("validation") or {}).get("predicted_expanded_uncertainty_deg")
            adaptive_runs = []
            for _ in range(args.adaptive_runs):
                adaptive = (
                    run_job(
                        client,
                        h,
                        {
                            **base,
                            "design": "adaptive",
                            "target_expanded_uncertainty_deg": round(float(target), 6),
                        },
                    )
                    if target
                    else {"state": "not run", "bench_seconds": None}
                )
                adaptive_runs.append(adaptive)
                label = f"{name}: adaptive, target {target:.5f}" if target else f"{name}: adaptive"
                print(row(label, adaptive), flush=True)
            for label, res in (
                ("seed 000 procedure", seed000),
                ("fixed", fixed),
                *(("adaptive", res) for res in adaptive_runs),
            ):
                if res.get("error"):
                    print(f"  {name} {label} error: {res['error']}", flush=True)
            floors = [
                design_floor(load_scenario(path), float(target), VALIDATION_POINTS, READINGS, share)
                if target
                else None
                for share in (None, MEAN_SHARE)
            ]
            results[name] = {
                "seed000_procedure": seed000,
                "fixed": fixed,
                "adaptive_runs": adaptive_runs,
                "target": target,
                **{
                    key: asdict(floor) | {"total": floor.total} if floor else None
                    for key, floor in zip(("floor", "floor_means"), floors, strict=True)
                },
            }
    print()
    for name, r in results.items():
        print(summary(name, r))
    if args.json:
        for r in results.values():
            for res in (r["seed000_procedure"], r["fixed"], *r["adaptive_runs"]):
                (res.get("validation") or {}).pop("points", None)
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
