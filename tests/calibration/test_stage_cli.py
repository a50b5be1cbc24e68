"""The offline contract for stage methods through the real console script (docs/datasets.md)."""

import csv
import json
import subprocess
import sys

import numpy as np
import pytest

from service.calibration.registry import FitOptions, get_method
from service.io.datasets import write_dataset
from service.io.model_files import write_model
from service.scenarios import load_scenario, run_scenario


def _tiltlab(*args, cwd):
    return subprocess.run(
        [sys.executable, "-m", "service", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("stage_cli")
    cols = run_scenario(load_scenario("seed000"), seed=4).columns
    write_dataset(d / "grid.csv", cols)
    line = cols["stage_y_deg"] == 0
    write_dataset(d / "one_line.csv", {k: v[line] for k, v in cols.items()})
    write_dataset(d / "three.csv", {k: v[[0, 40, 80]] for k, v in cols.items()})
    write_dataset(
        d / "targets.csv",
        {"target_x_deg": np.array([0.0, 6.0]), "target_y_deg": np.array([0.0, -9.0])},
    )
    return d


def _one_line_error(proc):
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in proc.stderr
    return lines[0]


def test_collinear_points_refused_for_the_homography(data_dir):
    p = _tiltlab(
        "calibrate",
        "--kind",
        "stage",
        "--method",
        "homography",
        "--input",
        "one_line.csv",
        "--out",
        "m.json",
        cwd=data_dir,
    )
    msg = _one_line_error(p)
    assert "one line" in msg and "H1" in msg
    assert not (data_dir / "m.json").exists()


def test_too_few_points_refused_for_the_kinematic_model(data_dir):
    msg = _one_line_error(
        _tiltlab(
            "calibrate",
            "--kind",
            "stage",
            "--method",
            "kinematic",
            "--input",
            "three.csv",
            "--out",
            "m.json",
            cwd=data_dir,
        )
    )
    assert "at least 5 distinct stage points, got 3" in msg


def test_model_without_measurement_sensor_cannot_correct(data_dir):
    cols = run_scenario(load_scenario("seed000"), seed=4).columns
    no_meas = {k: v for k, v in cols.items() if not k.startswith("meas_")}
    write_model(data_dir / "nm.json", get_method("stage", "kinematic").fit(no_meas, FitOptions()))
    msg = _one_line_error(
        _tiltlab(
            "correct", "--model", "nm.json", "--input", "grid.csv", "--out", "o.csv", cwd=data_dir
        )
    )
    assert "without meas_x_deg" in msg


def test_calibrate_correct_level_round(data_dir):
    p = _tiltlab(
        "calibrate",
        "--kind",
        "stage",
        "--method",
        "kinematic",
        "--input",
        "grid.csv",
        "--out",
        "k.json",
        "--loss",
        "soft_l1",
        cwd=data_dir,
    )
    assert p.returncode == 0, p.stderr
    assert (
        _tiltlab(
            "correct", "--model", "k.json", "--input", "grid.csv", "--out", "c.csv", cwd=data_dir
        ).returncode
        == 0
    )
    with open(data_dir / "c.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 81 and {
        "point",
        "ref_x_deg",
        "tilt_x_deg",
        "expanded_uncertainty_tilt_y_deg",
        "standard_uncertainty_tilt_y_deg",
        "coverage_factor_tilt_y",
    } <= set(rows[0])
    err = [abs(float(r["tilt_x_deg"]) - float(r["ref_x_deg"])) for r in rows]
    assert max(err) < 0.01  # the reference is the table tilt up to its noise
    assert (
        _tiltlab(
            "level", "--model", "k.json", "--targets", "targets.csv", "--out", "l.csv", cwd=data_dir
        ).returncode
        == 0
    )
    with open(data_dir / "l.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [set(r) for r in rows] == [
        {"target_x_deg", "target_y_deg", "stage_x_deg", "stage_y_deg"}
    ] * 2
    assert abs(float(rows[1]["stage_y_deg"]) + 9.0) < 0.3


def test_correct_names_its_uncertainties_standard_and_expanded(data_dir):
    """GUM: u is a standard uncertainty, U = k·u the expanded one; the columns say which is which,
    and the old u_* names (they held U) come only on request, equal to the expanded one."""
    assert (
        _tiltlab(
            "calibrate",
            "--kind",
            "stage",
            "--method",
            "homography",
            "--input",
            "grid.csv",
            "--out",
            "h.json",
            cwd=data_dir,
        ).returncode
        == 0
    )
    assert (
        _tiltlab(
            "correct", "--model", "h.json", "--input", "grid.csv", "--out", "new.csv", cwd=data_dir
        ).returncode
        == 0
    )
    p = _tiltlab(
        "correct",
        "--model",
        "h.json",
        "--input",
        "grid.csv",
        "--out",
        "old.csv",
        "--deprecated-u-columns",
        cwd=data_dir,
    )
    assert p.returncode == 0, p.stderr
    with open(data_dir / "new.csv", newline="") as fh:
        new = list(csv.DictReader(fh))
    with open(data_dir / "old.csv", newline="") as fh:
        old = list(csv.DictReader(fh))
    names = list(new[0])
    assert not any(n.startswith("u_") for n in names)
    assert len({n.lower() for n in names}) == len(names)  # no two names differ only by case
    for r, o in zip(new, old):
        for a in "xy":
            U, u = (
                float(r[f"expanded_uncertainty_tilt_{a}_deg"]),
                float(r[f"standard_uncertainty_tilt_{a}_deg"]),
            )
            k = float(r[f"coverage_factor_tilt_{a}"])
            # Student's t at the effective degrees of freedom (the reading noise's three-way
            # estimate has some tens)
            assert 1.96 < k < 2.6 and u * k == pytest.approx(U, rel=1e-4)
            assert o[f"u_tilt_{a}_deg"] == r[f"expanded_uncertainty_tilt_{a}_deg"]
        assert r["coverage_probability"] == "0.95"
    # an earlier output corrected again: its uncertainty columns are replaced, not carried beside
    # the new ones
    assert (
        _tiltlab(
            "correct", "--model", "h.json", "--input", "old.csv", "--out", "again.csv", cwd=data_dir
        ).returncode
        == 0
    )
    with open(data_dir / "again.csv", newline="") as fh:
        again = list(csv.DictReader(fh))
    assert list(again[0]) == names


def test_the_references_stated_noise_separates_the_two_sensors(data_dir):
    p = _tiltlab(
        "calibrate",
        "--kind",
        "stage",
        "--method",
        "kinematic",
        "--input",
        "grid.csv",
        "--out",
        "n.json",
        "--ref-noise-deg",
        "0.001",
        cwd=data_dir,
    )
    assert p.returncode == 0, p.stderr
    state = json.loads((data_dir / "n.json").read_text())["state"]
    assert "stated noise 0.001 deg" in state["meas_reading_noise_source"]
    assert state["meas_reading_standard_uncertainty_deg"] < state["meas_sigma_deg"]
    p = _tiltlab(
        "calibrate",
        "--kind",
        "scale",
        "--method",
        "poly1",
        "--input",
        "grid.csv",
        "--out",
        "x.json",
        "--ref-noise-deg",
        "0.001",
        cwd=data_dir,
    )
    assert p.returncode == 2 and "--ref-noise-deg" in p.stderr
