"""`tiltlab reproduce seed000|seed002|seed003|seed004|all`: rerun a paper's experiment, write its
report.

By default the reports go to a new folder named after the UTC time, so a run never rewrites
reports kept elsewhere (the repository's docs/reproduce is refreshed only when asked by name).
"""

from __future__ import annotations

import argparse
import datetime as dt
import importlib
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from service.commands._args import add_command
from service.errors import InputError

if TYPE_CHECKING:  # loaded by name in run(); named here so the layer gate sees them
    from service.reproduce import seed000, seed002, seed003, seed004  # noqa: F401

PAPERS = ("seed000", "seed002", "seed003", "seed004")
ABOUT = {
    "seed000": "stacked swing stages, homography calibration, and the kinematic chain against it",
    "seed002": "rotation angle from a triaxial sensor on an inclined axis (direct, IODSRA)",
    "seed003": "polynomial scale of an electrolytic sensor read through an ADC (its Table 1)",
    "seed004": "turntable inclinometer errors by reversal against a star-derived reference",
}


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    papers = "\n".join(f"  {name}  {text}" for name, text in ABOUT.items())
    parser = add_command(
        sub,
        "reproduce",
        "rerun a paper's experiment and write its report (Markdown and figures)",
        description="Rerun the experiments of the papers tiltlab's methods come from, on simulated "
        f"benches,\nand write one Markdown report per paper with its figures:\n{papers}",
        examples=["tiltlab reproduce seed003", "tiltlab reproduce all --out-dir reports/reproduce"],
    )
    parser.add_argument("paper", choices=[*PAPERS, "all"], help="which paper, or all")
    parser.add_argument(
        "--out-dir",
        default=None,
        metavar="FOLDER",
        help="folder for the reports, created if missing (default: a new folder "
        "tiltlab-reproduce-UTCSTAMP here)",
    )
    parser.set_defaults(handler=run)


def output_folder(out_dir: str | None) -> Path:
    """The folder to write into, created; an unusable one is an InputError naming it."""
    if out_dir is None:
        stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
        out = Path(f"tiltlab-reproduce-{stamp}")
        n = 1
        while out.exists():
            n += 1
            out = Path(f"tiltlab-reproduce-{stamp}-{n}")
    else:
        if out_dir == "":
            raise InputError("--out-dir is empty; give a folder name")
        out = Path(out_dir)
        if out.exists() and not out.is_dir():
            raise InputError(f"--out-dir {out}: is a file, not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".tiltlab-write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise InputError(
            f"--out-dir {out}: cannot create or write this folder ({exc.strerror})"
        ) from None
    return out


def run(args: argparse.Namespace) -> int:
    out = output_folder(args.out_dir)
    print(f"writing reports to {out}/", file=sys.stderr)
    for paper in PAPERS if args.paper == "all" else (args.paper,):
        t0 = time.perf_counter()
        module = importlib.import_module(f"service.reproduce.{paper}")
        module.run(out)
        _append_provenance(
            out / f"{paper}.md", getattr(args, "command_line", f"tiltlab reproduce {args.paper}")
        )
        print(
            f"{paper}: wrote {out / (paper + '.md')} in {time.perf_counter() - t0:.1f} s",
            file=sys.stderr,
        )
    return 0


def _inputs() -> dict[str, Path]:
    """The files a rerun reads: the scenario presets and the published data it compares with."""
    import service.calibration.data as data
    import service.scenarios as scenarios

    files = sorted((Path(scenarios.__file__).parent / "presets").glob("*.json"))
    files += sorted(Path(data.__file__).parent.glob("*.csv"))
    return {file.name: file for file in files}


def _append_provenance(report: Path, command: str) -> None:
    from service.io.provenance import provenance, provenance_lines

    lines = provenance_lines(provenance(command, _inputs()))
    with report.open("a", encoding="utf-8") as fh:
        fh.write("\n## Provenance\n\n" + "\n".join(f"- {line}" for line in lines) + "\n")
