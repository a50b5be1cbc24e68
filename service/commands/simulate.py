"""`tiltlab simulate`: a scenario (preset or file) to a dataset CSV; `--list` names the presets."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from service.commands._args import add_command, seed
from service.errors import InputError


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = add_command(
        sub,
        "simulate",
        "write a simulated bench run (dataset CSV) from a scenario",
        description="Simulate a calibration run: the scenario (a preset, see --list, or your own "
        "JSON file)\nstates the bench, the sensor errors, the point grid, the noise and "
        "the random seed; the\ndataset has the columns `calibrate` and `discrepancy` "
        "read (docs/datasets.md).",
        examples=[
            "tiltlab simulate --list",
            "tiltlab simulate --scenario seed000 --out seed000.csv",
            "tiltlab simulate --scenario my-bench.json --out run2.csv --seed 2",
        ],
    )
    parser.add_argument(
        "--scenario",
        metavar="NAME_OR_FILE",
        help="a preset name (see --list) or a scenario JSON file (docs/scenario.schema.json)",
    )
    parser.add_argument(
        "--out", metavar="FILE", help="the dataset CSV to write (required unless --list)"
    )
    parser.add_argument(
        "--seed", type=seed, default=None, help="random seed instead of the scenario's own"
    )
    parser.add_argument(
        "--list", action="store_true", help="print the presets, their kind and what they resemble"
    )
    parser.set_defaults(handler=run)


def list_presets() -> int:
    import shutil
    import textwrap

    from service.scenarios import load_scenario, preset_names

    # each description in full, wrapped to the terminal under its own column (never cut)
    width = max(60, shutil.get_terminal_size((100, 24)).columns)
    indent = " " * 24
    for name in preset_names():
        scenario = load_scenario(name)
        about = " ".join((scenario.description or "").split())
        print(
            textwrap.fill(
                about,
                width=width,
                initial_indent=f"{name:12s} {scenario.kind:10s} ",
                subsequent_indent=indent,
                break_on_hyphens=False,
            )
        )
    return 0


def run(args: argparse.Namespace) -> int:
    if args.list:
        if args.scenario or args.out is not None or args.seed is not None:
            raise InputError("--list prints the presets; it takes no --scenario, --out or --seed")
        return list_presets()
    missing = [
        option
        for option, value in (("--scenario", args.scenario), ("--out", args.out))
        if value is None
    ]
    if missing:
        raise InputError(f"required: {', '.join(missing)} (or --list to see the presets)")
    from service.io.datasets import check_not_overwriting, check_output_path, write_dataset
    from service.scenarios import load_scenario, run_scenario

    check_output_path(args.out)
    if Path(args.scenario).is_file():
        check_not_overwriting(args.out, scenario=args.scenario)
    scenario = load_scenario(args.scenario)
    result = run_scenario(scenario, seed=args.seed)
    write_dataset(args.out, result.columns)
    n = len(next(iter(result.columns.values())))
    print(
        f"wrote {n} {result.kind} rows of scenario {scenario.name!r} to {args.out}", file=sys.stderr
    )
    return 0
