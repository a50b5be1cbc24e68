"""The outlier rule's cut for each number of readings: the modified z-score that Gaussian readings
alone exceed, on any channel, in 1 % of points.

    python benchmarks/outlier_cuts.py [--draws 100000]

Prints the table `service.bench.readings.OUTLIER_CUTS` holds (readings: cut for 1, 2 and 3
channels). With few readings the median absolute deviation scatters widely, so a fixed cut of 3.5
rejects good readings in a fifth to a third of points (printed beside) and leaves a point's
standard deviation too small.
"""

from __future__ import annotations

import argparse

import numpy as np

from service.bench.readings import OUTLIER_FALSE_RATE, TABLED_READINGS, modified_z


def simulated_cut(
    n: int, channels: int, draws: int, rng: np.random.Generator
) -> tuple[float, float]:
    """(the cut Gaussian points of `n` readings exceed with OUTLIER_FALSE_RATE, the share of
    them a cut of 3.5 rejects a reading of)."""
    highest = []
    for start in range(0, draws, 5_000):
        block = rng.normal(0.0, 1.0, (min(5_000, draws - start), n, channels))
        highest.append(modified_z(block).max(axis=(1, 2)))
    top = np.concatenate(highest)
    return float(np.quantile(top, 1.0 - OUTLIER_FALSE_RATE)), float(np.mean(top > 3.5))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=100_000)
    args = ap.parse_args()
    rng = np.random.default_rng()
    print("readings: (cut 1, 2, 3 channels)  # share a cut of 3.5 rejects a good reading in")
    for n in TABLED_READINGS:
        cuts, shares = zip(*(simulated_cut(n, ch, args.draws, rng) for ch in (1, 2, 3)))
        print(
            f"    {n}: ({', '.join(f'{cut:.2f}' for cut in cuts)}),"
            f"  # {', '.join(f'{share:.0%}' for share in shares)}",
            flush=True,
        )


if __name__ == "__main__":
    main()
