"""`tiltlab discrepancy`: read the dataset, run the workflow, write the JSON report and the report
page.

Options (docs/datasets.md): --kind stage|scale, --input, --out REPORT.json, --sensor ref|meas,
--baseline linear|kinematic, --html (default: REPORT.html next to --out). Both files are
written atomically, and only after both are rendered, so a failure leaves nothing behind.

The instrument's noise level, when the lab knows it, comes from optional constant columns
(`noise_ref_x_deg`, `noise_ref_y_deg` or `noise_meas_*` for stage data, `noise_arcsec` for
scale data: 1-sigma of one reading); repeated points take precedence.

`--bench FILE` (stage) states the bench the data came from; without it the seed 000 bench is
assumed, said on stderr and recorded in the report, and data that are not whole pulses of it
are refused.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

from service.commands._args import add_command
from service.errors import InputError

if TYPE_CHECKING:
    from collections.abc import Mapping
    from pathlib import Path

    from service.calibration.model import CalibrationModel
    from service.datasets import Dataset
    from service.discrepancy.report_types import DiscrepancyReport, ReportInputs

# numpy, the dataset reader and the workflow are imported when the command runs, not by --help.


def _constant_column(ds: Dataset, col: str) -> float | None:
    import numpy as np

    if col not in ds.numeric:
        return None
    values = ds.numeric[col]
    bad = np.flatnonzero(values <= 0)
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"{ds.where(i + 1, col)}: a noise level must be positive, got {ds.text[col][i]}"
        )
    diff = np.flatnonzero(values != values[0])
    if diff.size:
        i = int(diff[0])
        raise InputError(
            f"{ds.where(i + 1, col)}: {ds.text[col][i]} differs from "
            f"the first row's {ds.text[col][0]}; the instrument's noise level is one value per axis"
        )
    return float(values[0])


def _output_paths(args: argparse.Namespace, kind: str) -> tuple[Path, Path, Path | None]:
    """The report, its page and the adopted model's paths, each checked before any work, so a bad
    one leaves no file behind."""
    from service.io.datasets import check_not_overwriting, check_output_path

    out = check_output_path(args.out)
    html_path = check_output_path(
        args.html if getattr(args, "html", None) else out.with_suffix(".html")
    )
    if html_path.resolve() == out.resolve():
        raise InputError(f"--html {html_path} would overwrite the JSON report --out {out}")
    check_not_overwriting(out, input=args.input)
    check_not_overwriting(html_path, "--html", input=args.input)
    adopt_path = None
    if getattr(args, "adopt", None):
        if kind != "stage":
            raise InputError("--adopt writes a kinematic stage model; kind 'scale' has none")
        adopt_path = check_output_path(args.adopt)
        if adopt_path.resolve() in (out.resolve(), html_path.resolve()):
            raise InputError(f"--adopt {adopt_path} would overwrite the report")
        check_not_overwriting(adopt_path, "--adopt", input=args.input)
    return out, html_path, adopt_path


def _stated_noise(ds: Dataset, nx: str, ny: str) -> list[float] | None:
    """The sensor's noise level per axis from its constant columns: both or neither."""
    noise = None
    cx, cy = _constant_column(ds, nx), _constant_column(ds, ny)
    if cx is not None or cy is not None:
        if cx is None or cy is None:
            raise InputError(
                f"{ds.source}: give both {nx!r} and {ny!r} (one noise level per axis), or neither"
            )
        noise = [cx, cy]
    return noise


def _stage_report(
    args: argparse.Namespace,
    baseline: str,
    inputs: ReportInputs,
    prov: Mapping[str, object],
    out: Path,
    adopt_path: Path | None,
) -> tuple[DiscrepancyReport, str, CalibrationModel | None]:
    """Stage data: the report, its page, and the calibration with the named effects added when
    --adopt asks for it."""
    from service.discrepancy.stage import stage_diagnosis
    from service.io.datasets import about, read_dataset

    sensor = getattr(args, "sensor", None) or "ref"
    nx, ny = f"noise_{sensor}_x_deg", f"noise_{sensor}_y_deg"
    ds = read_dataset(
        args.input,
        "stage",
        ("stage_x_deg", "stage_y_deg", f"{sensor}_x_deg", f"{sensor}_y_deg"),
        ("dir_x", "dir_y", "temp_c", "t_s", "point", nx, ny),
    )
    noise = _stated_noise(ds, nx, ny)
    from service.commands.offline import stage_bench_options

    stated = stage_bench_options("stage", getattr(args, "bench", None))
    adopted = None
    with about(args.input):
        report, page, result, _ = stage_diagnosis(
            ds.arrays(),
            sensor,
            baseline,
            noise,
            bench=stated.get("bench"),
            inputs=inputs,
            bench_source=stated.get("bench_source"),
            provenance=prov,
        )
        # the last step: the calibration with the named effects added
        if adopt_path is not None:
            from service.discrepancy.adopt import adopted_model, seen_labels_of
            from service.physics.stage import StageBench

            worm = sorted(
                {lab[:1] for lab in seen_labels_of(result.steps).get("periodic_error", [])}
            ) or ["x", "y"]
            adopted = adopted_model(
                ds.arrays(),
                report["named_effects"],
                sensor,
                stated.get("bench") or StageBench(),
                str(stated.get("bench_source") or report["bench"]["source"]),
                {
                    "what": f"the discrepancy report {out}",
                    "report": str(out),
                    "input": str(args.input),
                    "sensor": sensor,
                    "baseline": baseline,
                },
                worm_axes=worm,
            )
    return report, page, adopted


def _scale_report(
    args: argparse.Namespace, baseline: str, inputs: ReportInputs, prov: Mapping[str, object]
) -> tuple[DiscrepancyReport, str]:
    """Scale data: the report and its page; the stage-only options are refused."""
    from service.discrepancy.scale import scale_report
    from service.io.datasets import about, read_dataset

    if getattr(args, "bench", None) is not None:
        raise InputError("--bench describes a bench of stacked stages; kind 'scale' has none")
    if getattr(args, "sensor", None) is not None:
        raise InputError(
            "--sensor chooses between the two sensors of stage data; kind 'scale' has one "
            "sensor, leave it out"
        )

    if baseline not in ("linear", "poly1"):
        raise InputError(
            f"kind 'scale' has one baseline, poly1 (a straight line); --baseline {baseline} "
            "applies to stage data"
        )
    ds = read_dataset(
        args.input,
        "scale",
        (("ref_arcsec", "ref_deg"), "reading"),
        ("point", "temp_c", "t_s", "noise_arcsec"),
    )
    noise_arcsec = _constant_column(ds, "noise_arcsec")
    from service.discrepancy.report import clean_report, render_html

    with about(args.input):
        report, result, fam = scale_report(ds.arrays(), noise_arcsec, inputs=inputs)
    report["provenance"] = prov
    report = clean_report(report)
    page = render_html(report, result, fam)
    return report, page


def _tell_what_was_written(
    args: argparse.Namespace, kind: str, report: DiscrepancyReport, out: Path, html_path: Path
) -> None:
    """The closing lines on stderr: the chain, the final RMS against the noise, the files, the
    effects skipped, and the bench assumed."""
    chain = " → ".join(report["chain"])
    print(
        f"{kind}/{report['baseline']}: {chain}; final RMS "
        f"{', '.join(f'{value:.3g}' for value in report['final_rms'])} "
        f"{report['unit']} (noise {', '.join(f'{value:.3g}' for value in report['noise_level'])}, "
        f"{report['noise_source']}); wrote {out} and {html_path}",
        file=sys.stderr,
    )
    for skipped in report["skipped"]:
        print(f"  skipped {skipped['effect']}: {skipped['reason']}", file=sys.stderr)
    if kind == "stage" and getattr(args, "bench", None) is None:
        from service.commands.offline import assumed_bench_note

        print(assumed_bench_note(), file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    from service.io.datasets import write_text_atomic
    from service.io.provenance import provenance

    kind = args.kind
    baseline = getattr(args, "baseline", None) or "linear"
    inputs: ReportInputs = {"input": str(args.input)}
    # Both output paths are checked before the work, so a bad one leaves neither file behind.
    out, html_path, adopt_path = _output_paths(args, kind)
    adopted = None
    prov = provenance(
        getattr(args, "command_line", "tiltlab discrepancy"),
        {"input": args.input, "bench": getattr(args, "bench", None)},
    )
    if kind == "stage":
        report, page, adopted = _stage_report(args, baseline, inputs, prov, out, adopt_path)
    elif kind == "scale":
        report, page = _scale_report(args, baseline, inputs, prov)
    else:
        raise InputError(f"discrepancy supports kinds stage and scale, not {kind!r}")
    text = json.dumps(report, indent=1, ensure_ascii=False, allow_nan=False)
    write_text_atomic(out, text + "\n")
    try:
        write_text_atomic(html_path, page)
        if adopt_path is not None and adopted is not None:
            from service.io.model_files import write_model

            adopted.provenance = prov
            write_model(adopt_path, adopted)
    except BaseException:
        # a report without its page (or the model asked for) is half the result
        out.unlink(missing_ok=True)
        html_path.unlink(missing_ok=True)
        raise
    _tell_what_was_written(args, kind, report, out, html_path)
    return 0


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = add_command(
        sub,
        "discrepancy",
        "find, name and add the effects a bench model is missing",
        description="Fit a baseline model to a recorded run, look for structure left in the "
        "residuals, name the\nmissing effects one by one with their significance, and "
        "write a JSON report and its\nHTML page (docs/discrepancy.md; dataset columns "
        "in docs/datasets.md).",
        examples=[
            (
                "tiltlab discrepancy --kind stage --input seed000.csv --out report.json "
                "--bench bench.toml"
            ),
            "tiltlab discrepancy --kind scale --input adc.csv --out scale-report.json",
        ],
    )
    parser.add_argument(
        "--kind", required=True, choices=["stage", "scale"], help="what was calibrated"
    )
    parser.add_argument("--input", required=True, metavar="FILE", help="the dataset CSV")
    parser.add_argument("--out", required=True, metavar="FILE", help="the JSON report to write")
    parser.add_argument(
        "--sensor",
        choices=["ref", "meas"],
        default=None,
        help="stage only: which sensor's readings to explain (default: ref)",
    )
    parser.add_argument(
        "--baseline",
        choices=["linear", "kinematic"],
        default=None,
        help="stage only: the model the search starts from (default: linear; scale data always "
        "start from a straight line)",
    )
    parser.add_argument(
        "--bench",
        default=None,
        metavar="FILE",
        help="stage only: the bench the data came from (.toml bench configuration or .json "
        "scenario) (default: the seed 000 bench, said on stderr and in the report)",
    )
    parser.add_argument(
        "--html",
        default=None,
        metavar="FILE",
        help="the report page to write (default: the --out name with .html)",
    )
    parser.add_argument(
        "--adopt",
        default=None,
        metavar="MODEL.json",
        help="stage only: also write the kinematic calibration of the data with the named effects "
        "added (its state says which and from which report); refused when nothing was named",
    )
    parser.set_defaults(handler=run)
