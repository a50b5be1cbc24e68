"""`tiltlab calibrate | correct | level | discrepancy`: the offline contract of spec/datasets.md."""

from __future__ import annotations

import argparse
import sys

from service.calibration.registry import FitOptions, get_method
from service.datasets import about, check_not_overwriting, check_output_path, read_dataset, write_dataset
from service.errors import InputError
from service.modelio import read_model, write_model


def calibrate(args: argparse.Namespace) -> int:
    check_output_path(args.out)
    check_not_overwriting(args.out, input=args.input)
    method = get_method(args.kind, args.method)
    ds = read_dataset(args.input, args.kind, method.fit_required, method.fit_optional)
    options = FitOptions(rotation_deg=args.rotation_deg, loss=args.loss)
    with about(args.input):
        model = method.fit(ds.arrays(), options)
    write_model(args.out, model)
    stats = ", ".join(f"{c} rms {v['rms']:.4g}" for c, v in model.residuals.get("columns", {}).items())
    print(f"{args.kind}/{args.method}: fitted on {ds.n_rows} rows of {args.input}; {stats}; wrote {args.out}",
          file=sys.stderr)
    for note in model.notes:
        print(f"  note: {note}", file=sys.stderr)
    return 0


def correct(args: argparse.Namespace) -> int:
    check_output_path(args.out)
    check_not_overwriting(args.out, model=args.model, input=args.input)
    model = read_model(args.model)
    with about(args.model):
        method = get_method(model.kind, model.method)
    ds = read_dataset(args.input, model.kind, method.correct_required, method.correct_optional)
    out = method.correct(model, ds.arrays())
    cols = {**ds.passthrough(exclude=out), **out}
    write_dataset(args.out, cols)
    print(f"{model.kind}/{model.method}: corrected {ds.n_rows} rows; wrote {args.out}", file=sys.stderr)
    return 0


def level(args: argparse.Namespace) -> int:
    check_output_path(args.out)
    check_not_overwriting(args.out, model=args.model, targets=args.targets)
    model = read_model(args.model)
    if model.kind != "stage":
        raise InputError(f"{args.model}: level needs a stage model, this one is {model.kind!r}")
    with about(args.model):
        method = get_method(model.kind, model.method)
    ds = read_dataset(args.targets, "stage", ("target_x_deg", "target_y_deg"))
    with about(args.targets):
        out = method.level(model, ds.arrays())
    cols = {**ds.passthrough(exclude=out), **out}
    write_dataset(args.out, cols)
    print(f"stage/{model.method}: stage commands for {ds.n_rows} targets; wrote {args.out}", file=sys.stderr)
    return 0


def discrepancy(args: argparse.Namespace) -> int:
    from service.discrepancy import cli as discrepancy_cli

    return discrepancy_cli.run(args)
