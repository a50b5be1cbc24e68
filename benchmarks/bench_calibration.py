"""Benchmark of the stage calibration (in-process, not through the CLI).

    python benchmarks/bench_calibration.py
    python benchmarks/bench_calibration.py --single

Prints the time of one `kinematic` calibration of seed 000's 81-point grid (median of
repeats) and the throughput of `correct` (readings per second, with the GUM uncertainty).
With --single, the time of `correct` for one reading per call instead (what the daemon does
for each new reading), for every stage method. The figures are recorded in
docs/calibration-stage.md and README.md.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import numpy as np

from service.calibration.registry import FitOptions, get_method
from service.scenarios import load_scenario, run_scenario


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--readings", type=int, default=1_000_000)
    ap.add_argument(
        "--single",
        action="store_true",
        help="time correct on one reading per call, every stage method",
    )
    args = ap.parse_args()
    run = run_scenario(load_scenario("seed000"), seed=0)
    cols = run.columns
    if args.single:
        single(cols, args.repeats)
        return
    method = get_method("stage", "kinematic")
    method.fit(cols, FitOptions())  # warm-up (imports, caches)
    fit_s = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        model = method.fit(cols, FitOptions())
        fit_s.append(time.perf_counter() - t0)
    n = args.readings
    rng = np.random.default_rng(1)
    data = {"meas_x_deg": rng.uniform(-12, 12, n), "meas_y_deg": rng.uniform(-12, 12, n)}
    corr_s = []
    for _ in range(3):
        t0 = time.perf_counter()
        out = method.correct(model, data)
        corr_s.append(time.perf_counter() - t0)
    assert "u_tilt_x_deg" in out
    level_s = []
    targets = {
        "target_x_deg": rng.uniform(-12, 12, 100_000),
        "target_y_deg": rng.uniform(-12, 12, 100_000),
    }
    for _ in range(3):
        t0 = time.perf_counter()
        method.level(model, targets)
        level_s.append(time.perf_counter() - t0)
    print(
        f"machine: {platform.machine()}, python {platform.python_version()}, numpy {np.__version__}"
    )
    print(
        f"kinematic calibration, 81 points: median {statistics.median(fit_s):.3f} s "
        f"(min {min(fit_s):.3f}, max {max(fit_s):.3f}, {args.repeats} runs)"
    )
    print(
        f"kinematic correct with u_tilt: {n / min(corr_s):,.0f} readings/s (best of 3, {n:,} "
        "readings)"
    )
    print(f"kinematic level: {100_000 / min(level_s):,.0f} targets/s (best of 3, 100,000 targets)")


def single(cols: dict[str, np.ndarray], repeats: int, calls: int = 2000) -> None:
    """Per-call time of `correct` on one reading (best and median of `repeats` runs of `calls`
    calls)."""
    print(
        f"machine: {platform.machine()}, python {platform.python_version()}, numpy {np.__version__}"
    )
    reading = {"meas_x_deg": np.array([0.31]), "meas_y_deg": np.array([-0.2])}
    for name in ("kinematic", "homography", "axis-transform", "coupling"):
        method = get_method("stage", name)
        model = method.fit(cols, FitOptions())
        method.correct(model, reading)  # warm-up
        per_call = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            for _ in range(calls):
                method.correct(model, reading)
            per_call.append((time.perf_counter() - t0) / calls)
        print(
            f"{name} correct, one reading per call: best {min(per_call) * 1e6:.1f} us, median "
            f"{statistics.median(per_call) * 1e6:.1f} us ({repeats} runs of {calls:,} calls)"
        )


if __name__ == "__main__":
    main()
