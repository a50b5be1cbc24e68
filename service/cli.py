"""The `tiltlab` console script: the offline contract of spec/datasets.md plus service commands.

Every sub-command calls the same domain functions the service uses. Exit status: 0 success,
2 unusable input (message names what is missing), 1 any other failure; messages go to stderr.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from service.errors import InputError

Handler = Callable[[argparse.Namespace], int | None]


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # usage errors are input errors: exit 2, one line
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: a seed is a whole number >= 0")
    return value


def _cmd_simulate(args: argparse.Namespace) -> int:
    from service.commands import simulate

    return simulate.run(args)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from service.commands import offline

    return offline.calibrate(args)


def _cmd_correct(args: argparse.Namespace) -> int:
    from service.commands import offline

    return offline.correct(args)


def _cmd_level(args: argparse.Namespace) -> int:
    from service.commands import offline

    return offline.level(args)


def _cmd_discrepancy(args: argparse.Namespace) -> int:
    from service.commands import offline

    return offline.discrepancy(args)


def _cmd_reproduce(args: argparse.Namespace) -> int:
    from service.commands import reproduce

    return reproduce.run(args)


def _cmd_db(args: argparse.Namespace) -> int:
    from service.storage import cli as storage_cli

    return storage_cli.run(args)


def _cmd_serve(args: argparse.Namespace) -> int:
    from service.commands import serve

    return serve.run(args)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="tiltlab", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("simulate", help="write a dataset from a scenario (preset name or JSON file)")
    p.add_argument("--scenario", required=True, help="preset name (see --list) or path to a scenario JSON")
    p.add_argument("--out", required=True, help="CSV file to write")
    p.add_argument("--seed", type=_seed, default=None, help="override the scenario's random seed")
    p.set_defaults(handler=_cmd_simulate)

    p = sub.add_parser("calibrate", help="fit a calibration model to a dataset")
    p.add_argument("--kind", required=True, choices=["stage", "rotation", "scale", "turntable"])
    p.add_argument("--method", required=True)
    p.add_argument("--input", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--rotation-deg", type=float, default=180.0, help="turntable: the assumed rotation between the two positions of a pair")
    p.add_argument("--loss", default="linear", help="kinematic: robust loss of scipy.optimize.least_squares (linear, soft_l1, huber, cauchy)")
    p.set_defaults(handler=_cmd_calibrate)

    p = sub.add_parser("correct", help="apply a model to readings")
    p.add_argument("--model", required=True)
    p.add_argument("--input", required=True)
    p.add_argument("--out", required=True)
    p.set_defaults(handler=_cmd_correct)

    p = sub.add_parser("level", help="stage commands for wanted table tilts")
    p.add_argument("--model", required=True)
    p.add_argument("--targets", required=True)
    p.add_argument("--out", required=True)
    p.set_defaults(handler=_cmd_level)

    p = sub.add_parser("discrepancy", help="find, name and add the effects a bench model is missing")
    p.add_argument("--kind", required=True, choices=["stage", "scale"])
    p.add_argument("--input", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--sensor", choices=["ref", "meas"], default="ref")
    p.add_argument("--baseline", choices=["linear", "kinematic"], default="linear")
    p.add_argument("--html", default=None, help="also write the report page here (default: next to --out)")
    p.set_defaults(handler=_cmd_discrepancy)

    p = sub.add_parser("reproduce", help="rerun a paper's experiment and write its report")
    p.add_argument("paper", choices=["seed000", "seed002", "seed003", "seed004", "all"])
    p.add_argument("--out-dir", default="docs/reproduce")
    p.set_defaults(handler=_cmd_reproduce)

    p = sub.add_parser("db", help="database maintenance")
    dbsub = p.add_subparsers(dest="db_command", required=True, parser_class=_Parser)
    dbsub.add_parser("upgrade", help="bring the database to the current schema")
    dbsub.add_parser("current", help="print the schema revision of the database")
    q = dbsub.add_parser("downgrade", help="step the schema back")
    q.add_argument("revision", nargs="?", default="-1")
    dbsub.add_parser("verify", help="check hashes and chains of records and audit events")
    p.set_defaults(handler=_cmd_db)

    p = sub.add_parser("serve", help="run the lab service (HTTP API on a simulated or real bench)")
    p.add_argument("--host", default=None)
    p.add_argument("--port", type=int, default=None)
    p.set_defaults(handler=_cmd_serve)
    return parser


def _version() -> str:
    from service import __version__

    return f"tiltlab {__version__}"


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
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
        if _debug():
            raise
        return 1


def _debug() -> bool:
    import os

    return os.environ.get("TILTLAB_DEBUG", "") not in ("", "0")


if __name__ == "__main__":
    raise SystemExit(main())
