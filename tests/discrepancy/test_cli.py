"""`tiltlab discrepancy` as other software calls it: subprocess, files, exit status, stderr."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks.hidden_effects import bench_with_hidden
from service.io.datasets import write_dataset

ROOT = Path(__file__).resolve().parents[2]
TABLE1 = ROOT / "service" / "calibration" / "data" / "seed003_table1.csv"


def tiltlab(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "service", *args], capture_output=True, text=True, cwd=cwd
    )


@pytest.fixture(scope="module")
def bench_csv(tmp_path_factory):
    d = tmp_path_factory.mktemp("bench")
    hb = bench_with_hidden(0, {"backlash": 6.0})
    path = d / "bench.csv"
    cols = dict(hb.columns)
    cols["operator"] = ["A. N."] * len(cols["point"])  # unknown extra columns are allowed
    write_dataset(path, cols)
    return path, hb


def check_contract(rep, n_axes=2):
    for key in (
        "baseline",
        "named_effects",
        "steps",
        "skipped",
        "noise_level",
        "noise_source",
        "final_rms",
    ):
        assert key in rep, key
    assert isinstance(rep["baseline"], str)
    assert all(isinstance(e, str) for e in rep["named_effects"])
    for st in rep["steps"]:
        assert set(st) >= {"effect", "rms_before", "rms_after", "magnitude", "evidence"}
        assert len(st["rms_before"]) == len(st["rms_after"]) == n_axes
        assert isinstance(st["magnitude"], dict) and isinstance(st["evidence"], dict)
    for sk in rep["skipped"]:
        assert set(sk) >= {"effect", "reason"} and sk["reason"]
    assert len(rep["noise_level"]) == len(rep["final_rms"]) == n_axes
    assert rep["named_effects"] == list(dict.fromkeys(s["effect"] for s in rep["steps"]))


def test_stage_report_follows_the_contract_and_names_the_backlash(bench_csv, tmp_path):
    data, _ = bench_csv
    out = tmp_path / "report.json"
    r = tiltlab("discrepancy", "--kind", "stage", "--input", str(data), "--out", str(out))
    assert r.returncode == 0, r.stderr
    rep = json.loads(out.read_text())
    check_contract(rep)
    assert rep["baseline"] == "linear" and rep["sensor"] == "ref" and rep["unit"] == "deg"
    assert rep["named_effects"] == ["offaxis_coupling", "backlash"]
    assert rep["noise_source"] == "final residual"  # one pass, no noise columns
    page = (tmp_path / "report.html").read_text()
    assert page.count("data:image/png;base64,") >= 3  # residual maps, RMS chain, final histogram
    assert "offaxis_coupling" in page and "backlash" in page and "<script" not in page
    assert "wrote" in r.stderr


def test_kinematic_baseline_on_the_measurement_sensor_with_an_html_path(bench_csv, tmp_path):
    data, _ = bench_csv
    out, page = tmp_path / "r.json", tmp_path / "page.html"
    r = tiltlab(
        "discrepancy",
        "--kind",
        "stage",
        "--input",
        str(data),
        "--out",
        str(out),
        "--sensor",
        "meas",
        "--baseline",
        "kinematic",
        "--html",
        str(page),
    )
    assert r.returncode == 0, r.stderr
    rep = json.loads(out.read_text())
    check_contract(rep)
    assert rep["baseline"] == "kinematic" and rep["sensor"] == "meas"
    assert "backlash" in rep["named_effects"] and "offaxis_coupling" not in rep["named_effects"]
    assert page.exists() and not (tmp_path / "r.html").exists()


def test_noise_columns_are_the_instrument_specification(bench_csv, tmp_path):
    data, hb = bench_csv
    cols = dict(hb.columns)
    cols["noise_ref_x_deg"] = np.full(81, hb.sigma_deg)
    cols["noise_ref_y_deg"] = np.full(81, hb.sigma_deg)
    p = tmp_path / "withnoise.csv"
    write_dataset(p, cols)
    r = tiltlab(
        "discrepancy", "--kind", "stage", "--input", str(p), "--out", str(tmp_path / "r.json")
    )
    assert r.returncode == 0, r.stderr
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["noise_source"] == "instrument specification"
    # as written: degrees to 7 decimals
    assert rep["noise_level"] == pytest.approx([hb.sigma_deg] * 2, abs=1e-7)
    cols["noise_ref_x_deg"] = np.r_[np.full(80, hb.sigma_deg), 0.01]
    write_dataset(p, cols)
    r = tiltlab(
        "discrepancy", "--kind", "stage", "--input", str(p), "--out", str(tmp_path / "r2.json")
    )
    assert r.returncode == 2
    assert "row 81" in r.stderr and "noise_ref_x_deg" in r.stderr
    assert not (tmp_path / "r2.json").exists()


def test_scale_kind_on_table1(tmp_path):
    out = tmp_path / "t1.json"
    r = tiltlab("discrepancy", "--kind", "scale", "--input", str(TABLE1), "--out", str(out))
    assert r.returncode == 0, r.stderr
    rep = json.loads(out.read_text())
    check_contract(rep, n_axes=1)
    assert rep["baseline"] == "poly1" and rep["unit"] == "arcsec" and rep["named_effects"] == []
    assert (tmp_path / "t1.html").exists()
    r = tiltlab(
        "discrepancy",
        "--kind",
        "scale",
        "--input",
        str(TABLE1),
        "--out",
        str(tmp_path / "k.json"),
        "--baseline",
        "kinematic",
    )
    assert r.returncode == 2 and "poly1" in r.stderr


@pytest.mark.parametrize(
    "mutate,expect",
    [
        (lambda c: c.pop("ref_y_deg"), "ref_y_deg"),
        (lambda c: c.__setitem__("stage_x_deg", ["x"] + list(c["stage_x_deg"][1:])), "row 1"),
        (lambda c: c.__setitem__("dir_x", np.r_[c["dir_x"][:9], 2.0, c["dir_x"][10:]]), "row 10"),
        (
            lambda c: c.__setitem__(
                "ref_x_deg", np.r_[c["ref_x_deg"][:4], np.nan, c["ref_x_deg"][5:]]
            ),
            "row 5",
        ),
    ],
)
def test_bad_input_exits_2_naming_the_place_and_writes_nothing(bench_csv, tmp_path, mutate, expect):
    _, hb = bench_csv
    cols = {k: list(v) if k == "stage_x_deg" else v for k, v in hb.columns.items()}
    mutate(cols)
    p = tmp_path / "bad.csv"
    write_dataset(p, cols)
    out = tmp_path / "r.json"
    r = tiltlab("discrepancy", "--kind", "stage", "--input", str(p), "--out", str(out))
    assert r.returncode == 2, r.stderr
    assert expect in r.stderr and "bad.csv" in r.stderr
    assert not out.exists() and not (tmp_path / "r.html").exists()


def test_missing_file_and_missing_folder_exit_2(bench_csv, tmp_path):
    data, _ = bench_csv
    r = tiltlab(
        "discrepancy",
        "--kind",
        "stage",
        "--input",
        str(tmp_path / "nope.csv"),
        "--out",
        str(tmp_path / "r.json"),
    )
    assert r.returncode == 2 and "no such file" in r.stderr
    r = tiltlab(
        "discrepancy",
        "--kind",
        "stage",
        "--input",
        str(data),
        "--out",
        str(tmp_path / "no" / "r.json"),
    )
    assert r.returncode == 2 and "does not exist" in r.stderr
