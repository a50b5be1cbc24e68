"""Throughput of the stacked-stage forward model (docs/models.md §2 with every effect of the seed000
preset on).

    python benchmarks/bench_forward.py [--points 1000000] [--repeats 5]

Prints stage points per second (best and median of the repeats) for the full simulate_stage
call: pulse quantisation, stage errors, the kinematic chain for both sensors and the truth,
and every sensor reading error with noise.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from service.physics.stage import StageGeometry, simulate_stage
from service.scenarios import load_scenario, run_scenario


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--chunk",
        type=int,
        default=0,
        help="simulate in chunks of this many points (0: all at once)",
    )
    args = ap.parse_args()
    base = run_scenario(load_scenario("seed000"))
    bench, fx = base.bench, base.effects
    rng = np.random.default_rng(1)
    n = args.points
    cx = rng.uniform(-12, 12, n)
    cy = rng.uniform(-12, 12, n)
    dx = np.sign(rng.uniform(-1, 1, n))
    dy = np.sign(rng.uniform(-1, 1, n))
    temp = 20 + rng.uniform(-1, 1, n)
    t = np.arange(n) * 10.0
    geo = StageGeometry.from_effects(bench, fx)
    rates = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        step = args.chunk or n
        for i in range(0, n, step):
            s = slice(i, i + step)
            simulate_stage(bench, fx, cx[s], cy[s], dx[s], dy[s], temp[s], t[s], rng, geometry=geo)
        rates.append(n / (time.perf_counter() - t0))
    print(
        f"forward model, seed000 effects, {n} points x {args.repeats} repeats "
        f"(chunk {args.chunk or n}): best {max(rates):,.0f} points/s, median "
        f"{statistics.median(rates):,.0f} points/s"
    )


if __name__ == "__main__":
    main()
