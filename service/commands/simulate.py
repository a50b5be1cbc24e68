"""`tiltlab simulate`: a scenario (preset or file) to a dataset CSV."""

from __future__ import annotations

import argparse
import sys

from pathlib import Path

from service.datasets import check_not_overwriting, check_output_path, write_dataset
from service.scenarios import load_scenario, run_scenario


def run(args: argparse.Namespace) -> int:
    check_output_path(args.out)
    if Path(args.scenario).is_file():
        check_not_overwriting(args.out, scenario=args.scenario)
    scenario = load_scenario(args.scenario)
    result = run_scenario(scenario, seed=args.seed)
    write_dataset(args.out, result.columns)
    n = len(next(iter(result.columns.values())))
    print(f"wrote {n} {result.kind} rows of scenario {scenario.name!r} to {args.out}", file=sys.stderr)
    return 0
