"""Bad input a lab really produces, through the command line: exit 2, one line naming where, nothing left behind.

The CLI runs in-process (service.cli.main) to keep this fast; stage data are a small 5 x 5 grid.
"""

import json
import os
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.cli import main
from service.datasets import read_dataset, write_dataset
from service.errors import InputError
from service.scenarios import parse_scenario, run_scenario

SCALE = "point,ref_arcsec,reading\n" + "".join(f"{i},{100.0 * i + 0.5 * (i % 2)},{16 + 104 * i}\n" for i in range(8))
TARGETS = "target_x_deg,target_y_deg,note\n0,0,a\n2.5,-1.5,b\n"


def _stage_text() -> str:
    sc = parse_scenario({"kind": "stage", "grid": {"x_deg": [-10, -5, 0, 5, 10], "y_deg": [-10, -5, 0, 5, 10]}})
    cols = run_scenario(sc, seed=1).columns
    names = list(cols)
    rows = zip(*(cols[c] for c in names))
    return ",".join(names) + "\n" + "".join(",".join(repr(float(v)) for v in r) + "\n" for r in rows)


STAGE = _stage_text()


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("models")
    (d / "scale.csv").write_text(SCALE)
    (d / "stage.csv").write_text(STAGE)
    assert main(["calibrate", "--kind", "scale", "--method", "poly1", "--input", str(d / "scale.csv"),
                 "--out", str(d / "scale.json")]) == 0
    assert main(["calibrate", "--kind", "stage", "--method", "homography", "--input", str(d / "stage.csv"),
                 "--out", str(d / "stage.json")]) == 0
    return {"scale": d / "scale.json", "stage": d / "stage.json"}


def run(capsys, *argv) -> tuple[int, str]:
    capsys.readouterr()
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse's own exits
        rc = exc.code
    return rc, capsys.readouterr().err


def refused(capsys, folder, *argv) -> str:
    """Run; assert exit 2, one line of stderr, no traceback, and no new file (output or temporary) in `folder`."""
    before = sorted(os.listdir(folder))
    rc, err = run(capsys, *argv)
    assert rc == 2, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert sorted(os.listdir(folder)) == before
    return err.strip()


def commands(tmp_path, models, data: str, kind: str = "scale"):
    """Every command that reads `data` as its dataset, writing into tmp_path."""
    p = tmp_path / "in.csv"
    p.write_text(data, newline="") if isinstance(data, str) else p.write_bytes(data)
    if kind == "scale":
        return {
            "calibrate": ["calibrate", "--kind", "scale", "--method", "poly1", "--input", p, "--out", tmp_path / "m.json"],
            "correct": ["correct", "--model", models["scale"], "--input", p, "--out", tmp_path / "o.csv"],
            "discrepancy": ["discrepancy", "--kind", "scale", "--input", p, "--out", tmp_path / "r.json"],
        }
    return {
        "calibrate": ["calibrate", "--kind", "stage", "--method", "homography", "--input", p, "--out", tmp_path / "m.json"],
        "correct": ["correct", "--model", models["stage"], "--input", p, "--out", tmp_path / "o.csv"],
        "level": ["level", "--model", models["stage"], "--targets", p, "--out", tmp_path / "o.csv"],
    }


# --- output paths -----------------------------------------------------------------------------

def _all_commands(tmp_path, models, out):
    (tmp_path / "in.csv").write_text(SCALE)
    (tmp_path / "t.csv").write_text(TARGETS)
    return {
        "simulate": ["simulate", "--scenario", "seed003", "--out", out],
        "calibrate": ["calibrate", "--kind", "scale", "--method", "poly1", "--input", tmp_path / "in.csv", "--out", out],
        "correct": ["correct", "--model", models["scale"], "--input", tmp_path / "in.csv", "--out", out],
        "level": ["level", "--model", models["stage"], "--targets", tmp_path / "t.csv", "--out", out],
        "discrepancy": ["discrepancy", "--kind", "scale", "--input", tmp_path / "in.csv", "--out", out],
    }


@pytest.mark.parametrize("where,words", [
    ("missing/out.x", "does not exist"),
    ("adir", "is a folder"),
    ("afile/out.x", "is not a folder"),
    ("", "output path is empty"),
])
def test_an_output_path_that_cannot_be_a_file_is_refused(capsys, tmp_path, models, where, words):
    (tmp_path / "adir").mkdir()
    (tmp_path / "afile").write_text("x")
    out = str(tmp_path / where) if where else ""
    for name, argv in _all_commands(tmp_path, models, out).items():
        msg = refused(capsys, tmp_path, *argv)
        assert words in msg, (name, msg)
    assert (tmp_path / "afile").read_text() == "x" and not os.listdir(tmp_path / "adir")


def test_an_output_that_is_an_input_is_refused_and_the_input_kept(capsys, tmp_path, models):
    data, targets = tmp_path / "in.csv", tmp_path / "t.csv"
    data.write_text(SCALE)
    targets.write_text(TARGETS)
    model = tmp_path / "m.json"
    model.write_text(models["scale"].read_text())
    stage_model = tmp_path / "sm.json"
    stage_model.write_text(models["stage"].read_text())
    scenario = tmp_path / "sc.json"
    scenario.write_text(json.dumps({"kind": "scale", "grid": {"ref_arcsec": [0, 100, 200]}}))
    before = {p: p.read_bytes() for p in (data, targets, model, stage_model, scenario)}
    cases = [
        ["calibrate", "--kind", "scale", "--method", "poly1", "--input", data, "--out", data],
        ["correct", "--model", model, "--input", data, "--out", data],
        ["correct", "--model", model, "--input", data, "--out", tmp_path / "." / "m.json"],
        ["level", "--model", stage_model, "--targets", targets, "--out", targets],
        ["level", "--model", stage_model, "--targets", targets, "--out", stage_model],
        ["discrepancy", "--kind", "scale", "--input", data, "--out", data],
        ["discrepancy", "--kind", "scale", "--input", data, "--out", tmp_path / "r.json", "--html", data],
        ["simulate", "--scenario", scenario, "--out", scenario],
    ]
    for argv in cases:
        msg = refused(capsys, tmp_path, *argv)
        assert "so the input is kept" in msg, msg
    assert {p: p.read_bytes() for p in before} == before


def test_discrepancy_with_an_unwritable_page_leaves_no_report(capsys, tmp_path, models):
    (tmp_path / "in.csv").write_text(SCALE)
    (tmp_path / "page").mkdir()
    refused(capsys, tmp_path, "discrepancy", "--kind", "scale", "--input", tmp_path / "in.csv",
            "--out", tmp_path / "r.json", "--html", tmp_path / "page")
    (tmp_path / "r.html").mkdir()  # the default page path is a folder
    refused(capsys, tmp_path, "discrepancy", "--kind", "scale", "--input", tmp_path / "in.csv", "--out", tmp_path / "r.json")


# --- options ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,words", [
    ([], "required: command"),
    (["simulate", "--scenario", "seed003"], "required: --out"),
    (["simulate", "--scenario", "seed003", "--out", "{d}/o.csv", "--seed", "-1"], "a seed is a whole number >= 0"),
    (["simulate", "--scenario", "seed003", "--out", "{d}/o.csv", "--seed", "1.5"], "is not a whole number"),
    (["calibrate", "--kind", "bench", "--method", "poly1", "--input", "x", "--out", "y"], "invalid choice"),
    (["discrepancy", "--kind", "scale", "--input", "x", "--out", "y", "--sensor", "both"], "invalid choice"),
])
def test_usage_errors_exit_2_on_one_line(capsys, tmp_path, argv, words):
    msg = refused(capsys, tmp_path, *[a.format(d=tmp_path) for a in argv])
    assert words in msg and "usage" not in msg, msg


# --- model and scenario files -----------------------------------------------------------------------

@pytest.mark.parametrize("edit,words", [
    (lambda t: t[: len(t) // 2], "not valid JSON"),
    (lambda t: "kind,method\nstage,homography\n", "not valid JSON"),
    (lambda t: json.dumps({**json.loads(t), "format_version": 2}), "format_version: 2 is not supported"),
    (lambda t: json.dumps({**json.loads(t), "kind": "scale"}), "unknown method 'homography' for kind 'scale'"),
    (lambda t: json.dumps([json.loads(t)]), "a model is a JSON object"),
], ids=["truncated", "not-json", "future-version", "other-kind", "not-an-object"])
def test_a_broken_model_file_is_named(capsys, tmp_path, models, edit, words):
    model = tmp_path / "m.json"
    model.write_text(edit(models["stage"].read_text()))
    (tmp_path / "in.csv").write_text(STAGE)
    (tmp_path / "t.csv").write_text(TARGETS)
    for argv in (["correct", "--model", model, "--input", tmp_path / "in.csv", "--out", tmp_path / "o.csv"],
                 ["level", "--model", model, "--targets", tmp_path / "t.csv", "--out", tmp_path / "o.csv"]):
        msg = refused(capsys, tmp_path, *argv)
        assert str(model) in msg and (words in msg or "level needs a stage model" in msg), msg


def test_degenerate_data_are_refused_naming_the_file(capsys, tmp_path, models):
    one_point = "point,ref_arcsec,reading\n0,0,16\n0,0,16\n"
    for argv in commands(tmp_path, models, one_point).values():
        if argv[0] == "correct":
            continue
        msg = refused(capsys, tmp_path, *argv)
        assert str(tmp_path / "in.csv") in msg, msg
    (tmp_path / "t.csv").write_text("target_x_deg,target_y_deg\n89,89\n")
    msg = refused(capsys, tmp_path, "level", "--model", models["stage"], "--targets", tmp_path / "t.csv",
                  "--out", tmp_path / "o.csv")
    assert str(tmp_path / "t.csv") in msg, msg


