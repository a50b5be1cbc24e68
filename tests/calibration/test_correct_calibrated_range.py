"""`tiltlab correct --calibrated-range-column`: which corrected tilts lie within the table tilts the
model was fitted on; without the option the documented columns are unchanged."""

from __future__ import annotations

import csv
import json

import pytest

from service.cli import main


def _rows(path) -> list[dict[str, str]]:  # type: ignore[no-untyped-def]
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_correct_marks_tilts_outside_the_calibrated_range(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    run, model_path = tmp_path / "run.csv", tmp_path / "model.json"
    assert main(["simulate", "--scenario", "seed000", "--out", str(run)]) == 0
    assert (
        main(
            [
                "calibrate",
                "--kind",
                "stage",
                "--method",
                "kinematic",
                "--input",
                str(run),
                "--out",
                str(model_path),
            ]
        )
        == 0
    )
    seen = json.loads(model_path.read_text())["fit"]["table_tilt_range_deg"]
    rows = _rows(run)
    # readings: the run's own, and the same readings pushed well beyond the fitted range on x
    span = seen["x"][1] - seen["x"][0]
    readings = tmp_path / "readings.csv"
    with open(readings, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["meas_x_deg", "meas_y_deg", "name"])
        for r in rows:
            w.writerow([r["meas_x_deg"], r["meas_y_deg"], "run"])
            w.writerow([float(r["meas_x_deg"]) + 1.5 * span, r["meas_y_deg"], "beyond"])

    plain = tmp_path / "plain.csv"
    assert (
        main(["correct", "--model", str(model_path), "--input", str(readings), "--out", str(plain)])
        == 0
    )
    assert "in_calibrated_range" not in _rows(plain)[0]

    marked = tmp_path / "marked.csv"
    assert (
        main(
            [
                "correct",
                "--model",
                str(model_path),
                "--input",
                str(readings),
                "--out",
                str(marked),
                "--calibrated-range-column",
            ]
        )
        == 0
    )
    out = _rows(marked)
    for r in out:
        x, y = float(r["tilt_x_deg"]), float(r["tilt_y_deg"])
        inside = seen["x"][0] <= x <= seen["x"][1] and seen["y"][0] <= y <= seen["y"][1]
        assert r["in_calibrated_range"] == ("true" if inside else "false"), r
    assert all(r["in_calibrated_range"] == "false" for r in out if r["name"] == "beyond")
    run_rows = [r for r in out if r["name"] == "run"]
    assert sum(r["in_calibrated_range"] == "true" for r in run_rows) > len(run_rows) // 2

    # a model that states no range cannot say: refused, naming the option
    model = json.loads(model_path.read_text())
    del model["fit"]["table_tilt_range_deg"]
    old = tmp_path / "old-model.json"
    old.write_text(json.dumps(model))
    capsys.readouterr()
    assert (
        main(
            [
                "correct",
                "--model",
                str(old),
                "--input",
                str(readings),
                "--out",
                str(tmp_path / "o.csv"),
                "--calibrated-range-column",
            ]
        )
        == 2
    )
    assert "--calibrated-range-column" in capsys.readouterr().err
    assert not (tmp_path / "o.csv").exists()


@pytest.mark.parametrize("kind", ["scale"])
def test_calibrated_range_column_is_for_stage_models(tmp_path, capsys, kind) -> None:  # type: ignore[no-untyped-def]
    run, model_path = tmp_path / "run.csv", tmp_path / "model.json"
    assert main(["simulate", "--scenario", "seed003", "--out", str(run)]) == 0
    assert (
        main(
            [
                "calibrate",
                "--kind",
                kind,
                "--method",
                "poly1",
                "--input",
                str(run),
                "--out",
                str(model_path),
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(
            [
                "correct",
                "--model",
                str(model_path),
                "--input",
                str(run),
                "--out",
                str(tmp_path / "o.csv"),
                "--calibrated-range-column",
            ]
        )
        == 2
    )
    assert "applies to stage models only" in capsys.readouterr().err
