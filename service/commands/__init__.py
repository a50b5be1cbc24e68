"""The `tiltlab` command line, all of it in this package: one module per command, each with
`add_parser(sub)` (options, help, example) and the handler it sets; `_args` holds what they share.

Every command calls the same domain functions the service uses. Exit status: 0 success,
2 unusable input or configuration (a one-line message names what and where), 1 any other
failure; messages go to stderr.
"""

from __future__ import annotations

import argparse
import importlib
import os
import shlex
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

from service.commands._args import HelpFormatter, Parser, add_subcommands
from service.errors import InputError

# loaded by name below, when the parser is built; named here so the layer gate sees them
if TYPE_CHECKING:
    from service.commands import (  # noqa: F401
        db,
        devices,
        discrepancy,
        offline,
        reproduce,
        serve,
        sim,
        simulate,
        token,
        verify_certificate,
    )

# The order of `tiltlab --help`: working on recorded runs first, then the service and its upkeep.
COMMANDS = (
    "simulate",
    "calibrate:offline",
    "plan",
    "discrepancy",
    "reproduce",
    "serve",
    "sim",
    "devices",
    "db",
    "token",
    "verify_certificate",
)

OVERVIEW = """\
tiltlab calibrates biaxial inclinometers (tilt sensors) on motorised tilt stages and uses
them to measure and set tilt.

Work on recorded runs (CSV files; docs/datasets.md) without the service:
  tiltlab simulate --scenario seed000 --out run.csv        a simulated run to try things on
  tiltlab calibrate --kind stage --method kinematic --input run.csv --out model.json
  tiltlab correct --model model.json --input run.csv --out corrected.csv
  tiltlab level --model model.json --targets targets.csv --out commands.csv
  tiltlab discrepancy --kind stage --input run.csv --out report.json

Run the lab service (HTTP API, dashboard at http://127.0.0.1:8000/):
  tiltlab serve

`tiltlab COMMAND --help` shows a command's options, their defaults and an example."""


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="tiltlab", description=OVERVIEW, formatter_class=HelpFormatter)
    parser.add_argument(
        "--version", action="version", version=_version(), help="print the version and stop"
    )
    sub = add_subcommands(parser, "command")
    for entry in COMMANDS:
        module = entry.split(":")[-1]
        importlib.import_module(f"service.commands.{module}").add_parser(sub)
    return parser


def _version() -> str:
    from service import __version__

    return f"tiltlab {__version__}"


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv:
        parser.print_help()
        return 0
    args = parser.parse_args(argv)
    # for the provenance of what the command writes
    args.command_line = shlex.join(["tiltlab", *argv])
    try:
        return int(args.handler(args) or 0)
    except InputError as exc:
        print(f"tiltlab {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"tiltlab {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the contract is exit 1 with a message, not a traceback
        print(f"tiltlab {args.command}: failed: {type(exc).__name__}: {exc}", file=sys.stderr)
        if os.environ.get("TILTLAB_DEBUG", "") not in ("", "0"):
            raise
        return 1
