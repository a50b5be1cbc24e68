"""Options that do not apply to the kind or method given are refused, never silently ignored."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.cli import main


@pytest.fixture(scope="module")
def stage_csv(tmp_path_factory) -> Path:  # type: ignore[no-untyped-def]
    path = tmp_path_factory.mktemp("data") / "seed000.csv"
    assert main(["simulate", "--scenario", "seed000", "--out", str(path)]) == 0
    return path


@pytest.fixture(scope="module")
def scale_csv(tmp_path_factory) -> Path:  # type: ignore[no-untyped-def]
    path = tmp_path_factory.mktemp("data") / "seed003.csv"
    assert main(["simulate", "--scenario", "seed003", "--out", str(path)]) == 0
    return path


@pytest.mark.parametrize(
    "extra,word",
    [
        (["--method", "homography", "--loss", "huber"], "--loss"),
        (["--method", "kinematic", "--rotation-deg", "90"], "--rotation-deg"),
    ],
)
def test_calibrate_refuses_options_of_other_methods(
    stage_csv, tmp_path, capsys, extra, word
) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "model.json"
    assert (
        main(["calibrate", "--kind", "stage", "--input", str(stage_csv), "--out", str(out), *extra])
        == 2
    )
    err = capsys.readouterr().err
    assert word in err and "applies to" in err
    assert not out.exists()


def test_calibrate_refuses_bench_for_scale(scale_csv, tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "model.json"
    assert (
        main(
            [
                "calibrate",
                "--kind",
                "scale",
                "--method",
                "poly1",
                "--input",
                str(scale_csv),
                "--out",
                str(out),
                "--bench",
                "bench.toml",
            ]
        )
        == 2
    )
    assert "--bench" in capsys.readouterr().err and not out.exists()


def test_discrepancy_refuses_sensor_for_scale(scale_csv, tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "report.json"
    assert (
        main(
            [
                "discrepancy",
                "--kind",
                "scale",
                "--input",
                str(scale_csv),
                "--out",
                str(out),
                "--sensor",
                "meas",
            ]
        )
        == 2
    )
    assert "--sensor" in capsys.readouterr().err and not out.exists()


def test_the_defaults_still_fit(stage_csv, tmp_path) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "model.json"
    assert (
        main(
            [
                "calibrate",
                "--kind",
                "stage",
                "--method",
                "kinematic",
                "--input",
                str(stage_csv),
                "--out",
                str(out),
                "--loss",
                "soft_l1",
            ]
        )
        == 0
    )
    assert out.is_file()


def test_level_warns_about_targets_outside_the_calibrated_grid(stage_csv, tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    model = tmp_path / "model.json"
    assert (
        main(
            [
                "calibrate",
                "--kind",
                "stage",
                "--method",
                "homography",
                "--input",
                str(stage_csv),
                "--out",
                str(model),
            ]
        )
        == 0
    )
    targets = tmp_path / "targets.csv"
    targets.write_text("target_x_deg,target_y_deg\n0,0\n0.5,-0.25\n14,0\n")
    capsys.readouterr()
    assert (
        main(
            [
                "level",
                "--model",
                str(model),
                "--targets",
                str(targets),
                "--out",
                str(tmp_path / "c.csv"),
            ]
        )
        == 0
    )
    err = capsys.readouterr().err
    assert "1 target(s) outside the calibrated table tilts" in err and "rows 3" in err
    inside = tmp_path / "inside.csv"
    inside.write_text("target_x_deg,target_y_deg\n0,0\n0.5,-0.25\n")
    assert (
        main(
            [
                "level",
                "--model",
                str(model),
                "--targets",
                str(inside),
                "--out",
                str(tmp_path / "d.csv"),
            ]
        )
        == 0
    )
    assert "outside" not in capsys.readouterr().err
