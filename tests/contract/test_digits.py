"""Numbers are written with the digits they merit (docs/models.md, "Digits"), not 17."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import pytest

from service.cli import main
from service.io.datasets import format_value, read_dataset


@pytest.mark.parametrize(
    "col,value,text",
    [
        ("stage_x_deg", 0.1 + 0.2, "0.3"),
        ("tilt_x_deg", -1.23456789123, "-1.2345679"),
        ("expanded_uncertainty_tilt_x_deg", 2.5e-09, "0.0"),
        ("ref_north_arcsec", 1 / 3, "0.3333"),
        ("sx", 0.123456789012345, "0.123456789"),
        ("t_s", 1 / 3, "0.3333333333"),
        ("n1_a", -0.0, "0"),
        ("point", 3.0, "3"),
    ],
)
def test_rule_per_unit(col: str, value: float, text: str) -> None:
    assert format_value(col, value) == text


def _decimals(cell: str) -> int:
    return len(cell.split(".", 1)[1]) if "." in cell and "e" not in cell.lower() else 0


def test_simulated_and_corrected_files_carry_the_stated_digits(tmp_path: Path) -> None:
    data, model, out = tmp_path / "run.csv", tmp_path / "m.json", tmp_path / "corrected.csv"
    assert main(["simulate", "--scenario", "seed000", "--out", str(data)]) == 0
    assert (
        main(
            [
                "calibrate",
                "--kind",
                "stage",
                "--method",
                "homography",
                "--input",
                str(data),
                "--out",
                str(model),
            ]
        )
        == 0
    )
    assert main(["correct", "--model", str(model), "--input", str(data), "--out", str(out)]) == 0
    with out.open() as fh:
        rows = list(csv.DictReader(fh))
    for col in (
        "stage_x_deg",
        "ref_x_deg",
        "tilt_x_deg",
        "expanded_uncertainty_tilt_x_deg",
        "standard_uncertainty_tilt_x_deg",
    ):
        assert max(_decimals(r[col]) for r in rows) <= 7, col
    assert max(len(r["tilt_x_deg"]) for r in rows) < 14
    # and the file still reads back as whole pulses of the bench (the kinematic method accepts it)
    read_dataset(out, "stage", ("stage_x_deg", "stage_y_deg"))
    assert (
        main(
            [
                "calibrate",
                "--kind",
                "stage",
                "--method",
                "kinematic",
                "--input",
                str(data),
                "--out",
                str(tmp_path / "k.json"),
            ]
        )
        == 0
    )


def test_discrepancy_report_numbers_have_eight_significant_digits(tmp_path: Path) -> None:
    data, report = tmp_path / "s3.csv", tmp_path / "r.json"
    assert main(["simulate", "--scenario", "seed003", "--out", str(data)]) == 0
    assert main(["discrepancy", "--kind", "scale", "--input", str(data), "--out", str(report)]) == 0
    numbers = re.findall(r"-?\d+\.\d+(?:[eE][-+]?\d+)?", report.read_text())
    assert numbers
    for n in numbers:
        mantissa = n.lstrip("-").split("e")[0].split("E")[0].replace(".", "").lstrip("0")
        assert len(mantissa) <= 8, n
    json.loads(report.read_text())


def test_p_values_below_the_floor_are_a_bound() -> None:
    from service.discrepancy.report import _p

    assert _p(0.0) == "< 1e-300" and _p(0.012) == "0.012" and _p(None) == "—"
