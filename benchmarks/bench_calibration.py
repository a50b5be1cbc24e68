"""Benchmark of the stage calibration (in-process, not through the CLI).

    python benchmarks/bench_calibration.py

Prints the time of one `kinematic` calibration of seed 000's 81-point grid (median of
repeats) and the throughput of `correct` (readings per second, with the GUM uncertainty).
The figures are recorded in docs/calibration-stage.md.
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
    args = ap.parse_args()
    run = run_scenario(load_scenario("seed000"), seed=0)
    cols = run.columns
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
    targets = {"target_x_deg": rng.uniform(-12, 12, 100_000), "target_y_deg": rng.uniform(-12, 12, 100_000)}
    for _ in range(3):
        t0 = time.perf_counter()
        method.level(model, targets)
        level_s.append(time.perf_counter() - t0)
    print(f"machine: {platform.machine()}, python {platform.python_version()}, numpy {np.__version__}")
    print(f"kinematic calibration, 81 points: median {statistics.median(fit_s):.3f} s "
          f"(min {min(fit_s):.3f}, max {max(fit_s):.3f}, {args.repeats} runs)")
    print(f"kinematic correct with u_tilt: {n / min(corr_s):,.0f} readings/s (best of 3, {n:,} readings)")
    print(f"kinematic level: {100_000 / min(level_s):,.0f} targets/s (best of 3, 100,000 targets)")


if __name__ == "__main__":
    main()
