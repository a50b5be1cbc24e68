"""Coverage of the offline methods' expanded uncertainties against the simulated truth.

    python benchmarks/coverage.py                 # 200 noise realisations per case (minutes)
    python benchmarks/coverage.py --quick         # 20 per case: a smoke run, wide intervals
    python benchmarks/coverage.py --only rotation --realisations 400

Prints one row per method x scenario x axis (rotation: per angle of its sweep): the fraction of
validation points whose true value lies within the stated U (95 %), its Wilson 95 % interval,
the number of points and rms(error / U) (about 0.51 for an honest U at k ≈ 1.96). Definitions
in service/reproduce/coverage.py. The daemon path (GET /tilt, one reading and `average_s`) with
`--daemon N`: N calibrations per bench, each on a fresh in-process daemon, 60 stands each (about a
minute per calibration); `--daemon N --only daemon` runs only those rows. The averaged tilt over
many calibrations, made by the daemon's own chain without lines and clock
(service/reproduce/averaged_coverage.py), with `--averaged N`: N calibrations per bench, 5 stands
each (about 20 s per 300 calibrations); `--averaged N --only averaged` runs only those rows.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.instruments.sim.world import stage_scenario  # noqa: E402
from service.reproduce.averaged_coverage import averaged_rows  # noqa: E402
from service.reproduce.coverage import Row, daemon_rows, offline_cases  # noqa: E402


def line(r: Row) -> str:
    lo, hi = r.interval
    return (
        f"| {r.kind} | {r.method} | {r.scenario} | {r.axis} | {r.coverage:.3f} | "
        f"{lo:.3f}-{hi:.3f} | {r.n} | {r.rms_error_over_u:.2f} |"
    )


def one_calibration(scenario: str, k: int, got) -> None:  # type: ignore[no-untyped-def]
    """One calibration's figures on stderr: its stands share its parameter error, so they scatter
    from one calibration to the next more than a binomial interval of the readings would say."""
    single = (abs(got.errors) <= got.expanded).mean(axis=0)
    averaged = (abs(got.mean_errors) <= got.mean_expanded).mean(axis=0)
    print(
        f"  {scenario} calibration {k}: one reading x {single[0]:.3f} y {single[1]:.3f}; "
        f"averaged x {averaged[0]:.3f} y {averaged[1]:.3f} ({len(got.mean_errors)} stands, "
        f"{got.mean_readings.mean():.0f} readings each)",
        file=sys.stderr,
    )


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--realisations", type=int, default=200, help="noise realisations per case (default 200)"
    )
    ap.add_argument("--quick", action="store_true", help="20 realisations per case")
    ap.add_argument(
        "--only",
        default="",
        help="run only the cases whose name contains this (e.g. rotation, kinematic)",
    )
    ap.add_argument(
        "--daemon",
        type=int,
        default=0,
        metavar="N",
        help="also the daemon path: N calibrations per bench",
    )
    ap.add_argument(
        "--averaged",
        type=int,
        default=0,
        metavar="N",
        help="also the averaged tilt over N calibrations per bench by the daemon's chain",
    )
    ap.add_argument(
        "--stands",
        type=int,
        default=5,
        help="with --averaged: stands per calibration (default 5)",
    )
    ap.add_argument("--seed", type=int, default=0, help="with --averaged: the first seed")
    ap.add_argument(
        "--summary",
        action="store_true",
        help="rotation: one row per case (worst angle named) instead of one per angle",
    )
    args = ap.parse_args()
    n = 20 if args.quick else args.realisations
    print(f"coverage of U (95 %) over {n} noise realisations per case; Wilson 95 % intervals")
    print("| kind | method | scenario | axis | coverage | interval | points | rms(e/U) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for name, case in offline_cases(n):
        if args.only in ("daemon", "averaged") or (args.only and args.only not in name):
            continue
        t0 = time.perf_counter()
        rows = case()
        if args.summary and rows and rows[0].kind == "rotation":
            hits, total = sum(r.hits for r in rows), sum(r.n for r in rows)
            worst = min(rows, key=lambda r: r.coverage)
            rms = (sum(r.rms_error_over_u**2 * r.n for r in rows) / total) ** 0.5
            print(
                line(Row(worst.kind, worst.method, worst.scenario, "all angles", hits, total, rms))
            )
            print(line(worst).replace(f"| {worst.axis} |", f"| worst: {worst.axis} |"))
        else:
            for r in rows:
                print(line(r))
        print(f"  ({name}: {time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    if args.daemon:
        t0 = time.perf_counter()
        for r in daemon_rows(args.daemon, each=one_calibration):
            print(line(r))
        print(f"  (daemon: {time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    if args.averaged:
        t0 = time.perf_counter()
        benches = [(name, stage_scenario(name)) for name in ("seed000", "rough")]
        for r in averaged_rows(benches, args.averaged, args.stands, seed=args.seed):
            print(line(r))
        print(f"  (averaged: {time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
