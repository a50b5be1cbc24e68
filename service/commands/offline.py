"""`tiltlab calibrate | correct | level`: fit a model to a recorded run, apply it, level the stage.

The files they read and write are described in docs/datasets.md and docs/models.md.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, TypedDict

from service.commands._args import add_command, finite, row_count
from service.errors import InputError

# the methods and the dataset reader are imported when the command runs, not by --help
if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from service.calibration.model import CalibrationModel
    from service.datasets import Dataset
    from service.physics.stage import StageBench

# The methods, the dataset reader and numpy are imported by the commands that use them, so that
# `--help` starts at once.

KINDS = ("stage", "rotation", "scale", "turntable")
# The most data rows `calibrate` fits by default: a calibration run has a row per settled point (a
# grid of 10,000 is the daemon's own limit); what it costs per row is in docs/datasets.md ("Size").
MAX_FIT_ROWS = 100_000

# What each method is, in a line, for `tiltlab calibrate --help` (docs/calibration-*.md say more).
METHOD_HELP = {
    "stage": {
        "homography": "two plane-to-plane maps (reference sensor to stage, measurement to "
        "reference sensor), fitted linearly; fast, no bench needed",
        "kinematic": "the stacked stages' full kinematic chain (sensor mounting, axis offsets and "
        "tilts, scale) "
        "by nonlinear least squares, with uncertainties; uses --bench and --loss",
        "axis-transform": "comparison method: each sensing axis skewed against the stage axes, "
        "one linear axis transformation",
        "coupling": "comparison method: the off-axis coupling of the two stages alone, no mounting "
        "errors",
    },
    "rotation": {
        "direct": "rotation angle from the two horizontal axes, the vertical one assumed positive",
        "iodsra": "rotation angle from all three axes, switching equations near ±90° (inclined "
        "axis)",
        "iodsra-combined": "as iodsra, but the least-squares angle from all three axes together; "
        "never worse, better near ±45° and ±135°",
    },
    "scale": {
        "polyN": "polynomial of degree N (poly1 to poly6) turning ADC counts into angle, with "
        "F-tests for the degree",
    },
    "turntable": {
        "reversal": "zero, scale and axis errors from readings at azimuth pairs A and A + "
        "--rotation-deg, iterated against a reference tilt",
    },
}
# the robust losses of the kinematic fit
LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")


def _methods_text() -> str:
    import textwrap

    lines = ["methods per kind:"]
    for kind in KINDS:
        lines.append(f"  {kind}:")
        for name, text in METHOD_HELP[kind].items():
            lines += textwrap.wrap(
                text, 92, initial_indent=f"    {name:17s}", subsequent_indent=" " * 21
            )
    return "\n".join(lines)


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = add_command(
        sub,
        "calibrate",
        "fit a calibration model (MODEL.json) to a recorded run",
        description="Fit a calibration model to a dataset CSV and write it as MODEL.json "
        "(docs/models.md).\nThe dataset's columns per kind are in docs/datasets.md.\n\n"
        + _methods_text(),
        examples=[
            (
                "tiltlab calibrate --kind stage --method kinematic --input seed000.csv "
                "--out model.json --bench bench.toml"
            ),
            "tiltlab calibrate --kind scale --method poly2 --input adc.csv --out scale.json",
        ],
    )
    parser.add_argument("--kind", required=True, choices=KINDS, help="what was calibrated")
    parser.add_argument(
        "--method", required=True, help="the method, one of those listed above for the kind"
    )
    parser.add_argument("--input", required=True, metavar="FILE", help="the dataset CSV")
    parser.add_argument("--out", required=True, metavar="FILE", help="MODEL.json to write")
    parser.add_argument(
        "--rotation-deg",
        type=finite("an angle in degrees"),
        default=None,
        metavar="DEG",
        help="turntable only: the rotation between the two positions of a pair (default: 180)",
    )
    parser.add_argument(
        "--loss",
        choices=LOSSES,
        default=None,
        help="kinematic only: robust loss; soft_l1, huber, cauchy or arctan weigh outlying "
        "points down (default: linear, plain least squares)",
    )
    parser.add_argument(
        "--ref-noise-deg",
        type=finite("a standard deviation in degrees"),
        default=None,
        metavar="DEG",
        help="stage only: the reference sensor's noise, 1 sigma of one reading (e.g. from its "
        "certificate), so the uncertainty of a corrected tilt holds the measurement sensor's noise "
        "only; repeated readings at the points (same `point`) give it from the data instead",
    )
    parser.add_argument(
        "--bench",
        default=None,
        metavar="FILE",
        help="stage only: the bench the data came from: a bench configuration (.toml, its hardware "
        "table) or a scenario file (.json, its bench section) (default: the seed 000 bench, "
        "said on stderr and recorded in the model)",
    )
    parser.add_argument(
        "--max-rows",
        type=row_count,
        default=MAX_FIT_ROWS,
        metavar="N",
        help="refuse a dataset of more data rows than this, before reading it (a run has one "
        f"row per settled point; default: {MAX_FIT_ROWS:,})",
    )
    parser.set_defaults(handler=calibrate)

    parser = add_command(
        sub,
        "correct",
        "apply a model to readings: corrected tilt with its uncertainty",
        description="Apply MODEL.json to a dataset CSV of readings; the output keeps every input "
        "column and adds the\ncorrected values and their expanded uncertainties "
        "(columns per kind in docs/datasets.md).",
        examples=["tiltlab correct --model model.json --input readings.csv --out corrected.csv"],
    )
    parser.add_argument(
        "--model", required=True, metavar="FILE", help="MODEL.json from `tiltlab calibrate`"
    )
    parser.add_argument("--input", required=True, metavar="FILE", help="the readings CSV")
    parser.add_argument("--out", required=True, metavar="FILE", help="the CSV to write")
    parser.add_argument(
        "--deprecated-u-columns",
        action="store_true",
        help="also write the columns of earlier releases, u_<quantity> (e.g. u_tilt_x_deg): the "
        "EXPANDED uncertainty, the same as expanded_uncertainty_<quantity>; for software not "
        "yet reading the new names (deprecated: to be removed in a later release)",
    )
    parser.add_argument(
        "--calibrated-range-column",
        action="store_true",
        help="stage models only: also write `in_calibrated_range` (true or false): whether the "
        "corrected tilt lies within the table tilts the model was fitted on "
        "(MODEL.json fit.table_tilt_range_deg)",
    )
    parser.set_defaults(handler=correct)

    parser = add_command(
        sub,
        "level",
        "stage commands that give wanted table tilts (stage models only)",
        description="For each wanted table tilt in the targets CSV (columns target_x_deg, "
        "target_y_deg;\ndocs/datasets.md) write the stage commands that produce it, by "
        "the model's inverse.",
        examples=["tiltlab level --model model.json --targets targets.csv --out commands.csv"],
    )
    parser.add_argument("--model", required=True, metavar="FILE", help="a stage MODEL.json")
    parser.add_argument("--targets", required=True, metavar="FILE", help="targets CSV")
    parser.add_argument(
        "--out", required=True, metavar="FILE", help="the CSV of stage commands to write"
    )
    parser.set_defaults(handler=level)


def _refuse_options_that_do_not_apply(args: argparse.Namespace) -> None:
    _refuse_method_options(args)
    _refuse_stage_options(args)


def _refuse_method_options(args: argparse.Namespace) -> None:
    """--rotation-deg and --loss, which only the turntable and the kinematic stage method take."""
    if args.rotation_deg is not None and args.kind != "turntable":
        raise InputError(
            f"--rotation-deg applies to kind turntable only, not {args.kind!r}; leave it out"
        )
    if args.loss is not None and not (args.kind == "stage" and args.method == "kinematic"):
        raise InputError(
            f"--loss applies to the stage method kinematic only, not {args.kind}/{args.method}; "
            "leave it out"
        )


def _refuse_stage_options(args: argparse.Namespace) -> None:
    """--ref-noise-deg and --bench, which describe a stage bench: refused for other kinds."""
    if getattr(args, "ref_noise_deg", None) is not None and args.kind != "stage":
        raise InputError(
            f"--ref-noise-deg is the reference sensor's noise of a stage bench; kind {args.kind!r} "
            "has none"
        )
    if getattr(args, "ref_noise_deg", None) is not None and args.ref_noise_deg < 0:
        raise InputError(
            f"--ref-noise-deg {args.ref_noise_deg:g}: a standard deviation is not negative"
        )
    if args.bench is not None and args.kind != "stage":
        raise InputError(
            f"--bench describes a bench of stacked stages; kind {args.kind!r} has none"
        )


def calibrate(args: argparse.Namespace) -> int:
    from service.calibration.model import table_tilt_range
    from service.calibration.registry import FitOptions, get_method
    from service.io.datasets import about, check_not_overwriting, check_output_path, read_dataset
    from service.io.model_files import write_model
    from service.io.provenance import provenance

    check_output_path(args.out)
    check_not_overwriting(args.out, input=args.input)
    method = get_method(args.kind, args.method)
    _refuse_options_that_do_not_apply(args)
    ds = read_dataset(
        args.input, args.kind, method.fit_required, method.fit_optional, max_rows=args.max_rows
    )
    options = FitOptions(
        rotation_deg=180.0 if args.rotation_deg is None else args.rotation_deg,
        loss=args.loss or "linear",
        extra={
            **stage_bench_options(args.kind, getattr(args, "bench", None)),
            **(
                {"ref_noise_deg": args.ref_noise_deg}
                if getattr(args, "ref_noise_deg", None) is not None
                else {}
            ),
        },
    )
    # readings in radians or arc seconds are named here, not by a failed fit
    if args.kind == "stage":
        from service.io.datasets import check_stage_units
        from service.physics.stage import StageBench

        check_stage_units(ds, options.extra.get("bench", StageBench()).travel_deg)
    with about(args.input):
        model = method.fit(ds.arrays(), options)
    if args.kind == "stage":  # the table tilts the model has seen: `level` warns beyond them
        model.fit["table_tilt_range_deg"] = table_tilt_range(ds.arrays())
    model.provenance = provenance(
        getattr(args, "command_line", "tiltlab calibrate"),
        {"input": args.input, "bench": args.bench},
    )
    write_model(args.out, model)
    stats = ", ".join(
        f"{column} rms {residual['rms']:.4g}"
        for column, residual in model.residuals.get("columns", {}).items()
    )
    print(
        f"{args.kind}/{args.method}: fitted on {ds.n_rows} rows of {args.input}; {stats}; wrote "
        f"{args.out}",
        file=sys.stderr,
    )
    if args.kind == "stage" and getattr(args, "bench", None) is None:
        print(assumed_bench_note(), file=sys.stderr)
    for note in model.notes:
        print(f"  note: {note}", file=sys.stderr)
    return 0


def assumed_bench_note() -> str:
    from service.physics.stage import StageBench

    return (
        "  bench: none stated (--bench FILE): the seed 000 bench was assumed "
        f"({StageBench().describe()}); the output records it"
    )


class StatedBench(TypedDict, total=False):
    """`--bench FILE` as fit options: the bench's hardware and where it was read."""

    bench: StageBench
    bench_source: str


def stage_bench_options(kind: str, bench_path: str | None) -> StatedBench:
    """`--bench FILE` as fit options (empty without it: the methods then assume seed 000's and
    record so)."""
    if bench_path is None:
        return {}
    if kind != "stage":
        raise InputError(f"--bench describes a bench of stacked stages; kind {kind!r} has none")
    from service.instruments.bench_config import load_stage_bench

    bench, source = load_stage_bench(bench_path)
    return {"bench": bench, "bench_source": source}


def correct(args: argparse.Namespace) -> int:
    from service.calibration.model import stored_table_tilt_range
    from service.calibration.registry import get_method
    from service.io.datasets import (
        about,
        check_not_overwriting,
        check_output_path,
        read_dataset,
        write_dataset,
    )
    from service.io.model_files import read_model

    check_output_path(args.out)
    check_not_overwriting(args.out, model=args.model, input=args.input)
    model = read_model(args.model)
    with about(args.model):
        method = get_method(model.kind, model.method)
    seen = None
    if getattr(args, "calibrated_range_column", False):
        if model.kind != "stage":
            raise InputError(
                f"--calibrated-range-column applies to stage models only, not {model.kind!r}; "
                "leave it out"
            )
        seen = stored_table_tilt_range(model)
        if seen is None:
            raise InputError(
                f"{args.model}: --calibrated-range-column: the model states no calibrated range "
                "(fit.table_tilt_range_deg; models made before it was kept): fit it again with "
                "`tiltlab calibrate`"
            )
    ds = read_dataset(args.input, model.kind, method.correct_required, method.correct_optional)
    from service.calibration.uncertainty import COVERAGE
    from service.io.columns import uncertainty_columns

    result = method.correct(model, ds.arrays())
    quantities = tuple(output for output in method.outputs if not output.startswith("u_"))
    # the columns written: numbers, and text (the range flag; an input's columns passed through)
    out: dict[str, NDArray[np.float64] | list[str]] = {
        **uncertainty_columns(
            result, quantities, COVERAGE, deprecated=getattr(args, "deprecated_u_columns", False)
        )
    }
    if seen is not None:
        import numpy as np

        tilt_x = np.asarray(out["tilt_x_deg"], dtype=float)  # the corrected tilts, as they are
        tilt_y = np.asarray(out["tilt_y_deg"], dtype=float)
        inside = (
            (seen["x"][0] <= tilt_x)
            & (tilt_x <= seen["x"][1])
            & (seen["y"][0] <= tilt_y)
            & (tilt_y <= seen["y"][1])
        )
        out["in_calibrated_range"] = ["true" if is_inside else "false" for is_inside in inside]
    # an input that is itself an earlier output: its uncertainty columns are replaced, not kept
    # beside the new ones
    stale = set(out) | {f"u_{quantity}" for quantity in quantities}
    cols: dict[str, NDArray[np.float64] | list[str]] = {**ds.passthrough(exclude=stale), **out}
    write_dataset(args.out, cols)
    print(
        f"{model.kind}/{model.method}: corrected {ds.n_rows} rows; wrote {args.out}",
        file=sys.stderr,
    )
    return 0


def level(args: argparse.Namespace) -> int:
    from service.calibration.registry import levelling_method
    from service.io.datasets import (
        about,
        check_not_overwriting,
        check_output_path,
        read_dataset,
        write_dataset,
    )
    from service.io.model_files import read_model

    check_output_path(args.out)
    check_not_overwriting(args.out, model=args.model, targets=args.targets)
    model = read_model(args.model)
    if model.kind != "stage":
        raise InputError(f"{args.model}: level needs a stage model, this one is {model.kind!r}")
    with about(args.model):
        method = levelling_method(model.kind, model.method)
    ds = read_dataset(args.targets, "stage", ("target_x_deg", "target_y_deg"))
    with about(args.targets):
        out = method.level(model, ds.arrays())
    _warn_outside_calibrated_range(model, ds, args.targets)
    cols: dict[str, NDArray[np.float64] | list[str]] = {**ds.passthrough(exclude=out), **out}
    write_dataset(args.out, cols)
    print(
        f"stage/{model.method}: stage commands for {ds.n_rows} targets; wrote {args.out}",
        file=sys.stderr,
    )
    return 0


def _warn_outside_calibrated_range(model: CalibrationModel, ds: Dataset, targets_path: str) -> None:
    """A target beyond the table tilts the model was fitted on is an extrapolation: say which
    rows."""
    seen = model.fit.get("table_tilt_range_deg")
    if not isinstance(seen, dict):
        return
    arrays = ds.arrays()
    outside = []
    for axis in "xy":
        lo, hi = seen[axis]
        values = arrays[f"target_{axis}_deg"]
        outside += [i for i, value in enumerate(values) if not lo <= value <= hi]
    if outside:
        rows = sorted(set(outside))
        shown = ", ".join(str(row + 1) for row in rows[:5]) + (", …" if len(rows) > 5 else "")
        print(
            f"  warning: {targets_path}: {len(rows)} target(s) outside the calibrated table "
            f"tilts (x {seen['x'][0]:g} to {seen['x'][1]:g}°, y {seen['y'][0]:g} to "
            f"{seen['y'][1]:g}°), rows {shown}: the commands there are extrapolated",
            file=sys.stderr,
        )
