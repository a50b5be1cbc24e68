"""`tiltlab calibrate --kind stage` checks the units of a run before fitting it: a `_deg` column in
radians, arc seconds or another unit is refused (exit 2) naming the column and the unit it looks
like, not left to a fit that fails far from the cause."""

from __future__ import annotations

import csv
import math
import subprocess
import sys
from pathlib import Path

import pytest

SIMULATED = {}


def run_of(tmp_path: Path) -> list[dict[str, str]]:
    if "rows" not in SIMULATED:
        out = tmp_path / "seed000.csv"
        made = subprocess.run(
            [
                sys.executable,
                "-m",
                "service",
                "simulate",
                "--scenario",
                "seed000",
                "--out",
                str(out),
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert made.returncode == 0, made.stderr
        SIMULATED["rows"] = list(csv.DictReader(out.open()))
    return SIMULATED["rows"]


def calibrate(
    tmp_path: Path, columns: tuple[str, ...], convert
) -> subprocess.CompletedProcess[str]:
    rows = run_of(tmp_path)
    path = tmp_path / "run.csv"
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, list(rows[0]))
        writer.writeheader()
        for row in rows:
            writer.writerow({**row, **{c: repr(convert(float(row[c]))) for c in columns}})
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "service",
            "calibrate",
            "--kind",
            "stage",
            "--method",
            "homography",
            "--input",
            str(path),
            "--out",
            str(tmp_path / "model.json"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.parametrize(
    ("columns", "convert", "named", "unit"),
    [
        (("ref_x_deg", "ref_y_deg"), math.radians, "column ref_x_deg", "radians"),
        (("meas_x_deg", "meas_y_deg"), lambda v: 1000 * v, "meas_x_deg", "millidegrees"),
        (("stage_x_deg", "stage_y_deg"), math.radians, "column stage_x_deg", "radians"),
    ],
)
def test_a_column_in_another_unit_is_named(tmp_path, columns, convert, named, unit):
    result = calibrate(tmp_path, columns, convert)
    assert result.returncode == 2, result.stderr
    assert named in result.stderr and "degrees" in result.stderr, result.stderr
    # readings of thousands are refused as beyond the table's tilt, row and column named
    if unit != "millidegrees":
        assert f"looks like {unit}" in result.stderr, result.stderr
    assert not (tmp_path / "model.json").exists()


def test_arc_seconds_beyond_any_tilt_are_refused_naming_the_cell(tmp_path):
    result = calibrate(tmp_path, ("ref_x_deg",), lambda v: 3600 * v)
    assert (
        result.returncode == 2
        and "column 'ref_x_deg'" in result.stderr
        and "row 1" in result.stderr
    ), result.stderr


def test_degrees_pass(tmp_path):
    result = calibrate(tmp_path, (), float)
    assert result.returncode == 0, result.stderr
