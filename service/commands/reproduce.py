"""`tiltlab reproduce seed000|seed002|seed003|seed004|all`: rerun a paper's experiment, write its report."""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path

PAPERS = ("seed000", "seed002", "seed003", "seed004")


def run(args: argparse.Namespace) -> int:
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for paper in PAPERS if args.paper == "all" else (args.paper,):
        t0 = time.perf_counter()
        module = importlib.import_module(f"service.reproduce.{paper}")
        module.run(out)
        print(f"{paper}: wrote {out / (paper + '.md')} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return 0
