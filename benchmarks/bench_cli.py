"""Benchmark of the command line's start-up: `tiltlab --help` and `tiltlab calibrate --help`.

    python benchmarks/bench_cli.py [--repeats 5]

Each command runs as a fresh process (the same interpreter, `python -m service.cli`), as a
user scripting many files pays it. The yardstick, measured in the same run and interleaved
with the commands so that load hits all alike, is `python -c "import numpy"`; the ratio to it
holds on a shared machine where the seconds do not. Prints the medians, the ratios and the
load average before and after.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

CASES = {
    "python -c 'import numpy'": [sys.executable, "-c", "import numpy"],
    "tiltlab --help": [sys.executable, "-m", "service.cli", "--help"],
    "tiltlab calibrate --help": [sys.executable, "-m", "service.cli", "calibrate", "--help"],
}


def once(argv: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    load_before = os.getloadavg()
    for argv in CASES.values():  # warm the file cache
        once(argv)
    times: dict[str, list[float]] = {name: [] for name in CASES}
    for _ in range(args.repeats):
        for name, argv in CASES.items():
            times[name].append(once(argv))
    load_after = os.getloadavg()
    yardstick = statistics.median(times["python -c 'import numpy'"])
    print(
        f"load average (1, 5, 15 min): before {load_before[0]:.2f} {load_before[1]:.2f} "
        f"{load_before[2]:.2f}, "
        f"after {load_after[0]:.2f} {load_after[1]:.2f} {load_after[2]:.2f}; {os.cpu_count()} cores"
    )
    for name, t in times.items():
        print(
            f"{name:26s} median {statistics.median(t):.3f} s of {args.repeats} (min {min(t):.3f}, "
            f"max {max(t):.3f})"
            f"  {statistics.median(t) / yardstick:5.1f} x import numpy"
        )


if __name__ == "__main__":
    main()
