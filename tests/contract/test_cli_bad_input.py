"""Bad input a lab really produces, through the command line: exit 2, one line naming where, nothing
left behind.

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
from service.errors import InputError
from service.io.datasets import read_dataset, write_dataset
from service.scenarios import parse_scenario, run_scenario

SCALE = "point,ref_arcsec,reading\n" + "".join(
    f"{i},{100.0 * i + 0.5 * (i % 2)},{16 + 104 * i}\n" for i in range(8)
)
TARGETS = "target_x_deg,target_y_deg,note\n0,0,a\n2.5,-1.5,b\n"


def _stage_text() -> str:
    sc = parse_scenario(
        {"kind": "stage", "grid": {"x_deg": [-10, -5, 0, 5, 10], "y_deg": [-10, -5, 0, 5, 10]}}
    )
    cols = run_scenario(sc, seed=1).columns
    names = list(cols)
    rows = zip(*(cols[c] for c in names))
    return (
        ",".join(names) + "\n" + "".join(",".join(repr(float(v)) for v in r) + "\n" for r in rows)
    )


STAGE = _stage_text()


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("models")
    (d / "scale.csv").write_text(SCALE)
    (d / "stage.csv").write_text(STAGE)
    assert (
        main(
            [
                "calibrate",
                "--kind",
                "scale",
                "--method",
                "poly1",
                "--input",
                str(d / "scale.csv"),
                "--out",
                str(d / "scale.json"),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "calibrate",
                "--kind",
                "stage",
                "--method",
                "homography",
                "--input",
                str(d / "stage.csv"),
                "--out",
                str(d / "stage.json"),
            ]
        )
        == 0
    )
    return {"scale": d / "scale.json", "stage": d / "stage.json"}


def run(capsys, *argv) -> tuple[int, str]:
    capsys.readouterr()
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse's own exits
        rc = exc.code
    return rc, capsys.readouterr().err


def refused(capsys, folder, *argv) -> str:
    """Run; assert exit 2, one line of stderr, no traceback, and no new file (output or temporary)
    in `folder`."""
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
            "calibrate": [
                "calibrate",
                "--kind",
                "scale",
                "--method",
                "poly1",
                "--input",
                p,
                "--out",
                tmp_path / "m.json",
            ],
            "correct": [
                "correct",
                "--model",
                models["scale"],
                "--input",
                p,
                "--out",
                tmp_path / "o.csv",
            ],
            "discrepancy": [
                "discrepancy",
                "--kind",
                "scale",
                "--input",
                p,
                "--out",
                tmp_path / "r.json",
            ],
        }
    return {
        "calibrate": [
            "calibrate",
            "--kind",
            "stage",
            "--method",
            "homography",
            "--input",
            p,
            "--out",
            tmp_path / "m.json",
        ],
        "correct": [
            "correct",
            "--model",
            models["stage"],
            "--input",
            p,
            "--out",
            tmp_path / "o.csv",
        ],
        "level": ["level", "--model", models["stage"], "--targets", p, "--out", tmp_path / "o.csv"],
    }


# --- how Excel and other lab software write CSV -----------------------------------------


def _semicolon(text):
    return text.replace(",", ";")


def _decimal_comma(text):
    return text.replace(",", ";").replace(".", ",")


@pytest.mark.parametrize(
    "kind,base",
    [("scale", SCALE), ("stage", STAGE), ("stage", TARGETS)],
    ids=["scale", "stage", "targets"],
)
@pytest.mark.parametrize(
    "dialect",
    [_semicolon, _decimal_comma, lambda t: t.replace(",", "\t")],
    ids=["semicolon", "decimal-comma", "tab"],
)
def test_a_file_not_separated_by_commas_is_refused_naming_the_separator(
    capsys, tmp_path, models, kind, base, dialect
):
    cmds = commands(tmp_path, models, dialect(base), kind)
    names = ["level"] if base is TARGETS else [c for c in cmds if c != "level"]
    for name in names:
        msg = refused(capsys, tmp_path, *cmds[name])
        assert (
            str(tmp_path / "in.csv") in msg
            and "line 1" in msg
            and "separator must be a comma" in msg
        ), msg


def test_a_decimal_comma_in_a_quoted_cell_is_named(capsys, tmp_path, models):
    lines = SCALE.splitlines()
    lines[3] = '2,"200,5",224'
    msg = refused(
        capsys, tmp_path, *commands(tmp_path, models, "\n".join(lines) + "\n")["calibrate"]
    )
    assert "row 3 (line 4), column 'ref_arcsec'" in msg and "decimal mark must be '.'" in msg, msg


@pytest.mark.parametrize(
    "dialect",
    [
        lambda t: "\ufeff" + t,  # Excel's "CSV UTF-8"
        lambda t: t.replace("\n", "\r\n"),  # Windows line endings
        lambda t: (
            "\n".join(",".join(f'"{c}"' for c in line.split(",")) for line in t.splitlines()) + "\n"
        ),
        lambda t: (
            "\n".join(" , ".join(f" {c} " for c in line.split(",")) for line in t.splitlines())
            + "\n"
        ),
    ],
    ids=["bom", "crlf", "quoted", "spaces"],
)
def test_what_spreadsheets_add_is_accepted_and_reads_the_same(tmp_path, dialect):
    plain, other = tmp_path / "plain.csv", tmp_path / "other.csv"
    plain.write_text(STAGE, newline="")
    other.write_text(dialect(STAGE), newline="")
    cols = ("stage_x_deg", "stage_y_deg", "ref_x_deg", "ref_y_deg")
    a, b = (
        read_dataset(plain, "stage", cols, ("t_s", "dir_x")),
        read_dataset(other, "stage", cols, ("t_s", "dir_x")),
    )
    assert a.header == b.header and all(np.array_equal(a[c], b[c]) for c in a.numeric)


# --- cells ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "cell,words",
    [
        ("1_0", "is not a number"),  # float() would read 10
        ("\u0661\u0662", "is not a number"),  # Arabic-Indic digits: float() would read 12
        ("0x10", "is not a number"),
        ("0\x1f", "is not a number"),  # a control code is not padding, though str.strip() drops it
        ("1\u2003", "is not a number"),  # nor is a Unicode space
        ("NaN", "not a finite number"),
        ("-inf", "not a finite number"),
        ("Infinity", "not a finite number"),
        ("1e400", "not a finite number"),
        ("", "empty cell"),
    ],
)
def test_a_bad_number_is_named_by_file_row_and_column(capsys, tmp_path, models, cell, words):
    lines = SCALE.splitlines()
    lines[4] = f'3,"{cell}",328'
    for name, argv in commands(tmp_path, models, "\n".join(lines) + "\n").items():
        if name == "correct":  # correct does not use the reference column
            continue
        msg = refused(capsys, tmp_path, *argv)
        assert (
            f"{tmp_path / 'in.csv'}, row 4 (line 5), column 'ref_arcsec'" in msg and words in msg
        ), msg


_PLAIN = r"[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?"


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    cell=st.one_of(
        st.text(
            st.characters(blacklist_characters="\r\n", blacklist_categories=("Cs",)), max_size=12
        ),
        st.from_regex(_PLAIN, fullmatch=True),
        st.floats(allow_nan=True, allow_infinity=True).map(repr),
    )
)
def test_a_cell_reads_as_its_plain_decimal_value_or_is_refused_by_row_and_column(tmp_path, cell):
    p = tmp_path / "c.csv"
    write_dataset(p, {"ref_arcsec": [cell], "reading": ["1"]})
    try:
        ds = read_dataset(p, "scale", ("ref_arcsec",))
    except InputError as exc:
        assert f"{p}, row 1 (line 2), column 'ref_arcsec'" in str(exc), str(exc)
        return
    assert re.fullmatch(_PLAIN, cell.strip(" \t"))
    assert ds["ref_arcsec"][0] == float(cell) and np.isfinite(ds["ref_arcsec"][0])


def test_row_and_line_stay_right_past_blank_lines(capsys, tmp_path, models):
    lines = SCALE.splitlines()
    lines[5] = "4,400,xyz"
    text = lines[0] + "\n\n" + "\n".join(lines[1:3]) + "\n,,\n" + "\n".join(lines[3:]) + "\n"
    msg = refused(capsys, tmp_path, *commands(tmp_path, models, text)["calibrate"])
    assert "row 5 (line 8), column 'reading'" in msg, msg


def test_a_column_that_is_entirely_empty_says_so(capsys, tmp_path, models):
    text = "point,ref_arcsec,reading\n" + "".join(f"{i},,{i}\n" for i in range(4))
    msg = refused(capsys, tmp_path, *commands(tmp_path, models, text)["calibrate"])
    assert "row 1 (line 2), column 'ref_arcsec'" in msg and "empty in every row" in msg, msg


@pytest.mark.parametrize(
    "data,words",
    [
        ("", "empty file"),
        ("point,ref_arcsec,reading\n", "no data rows"),
        (
            "point,ref_arcsec,reading,reading\n0,0,1,1\n1,1,2,2\n",
            "'reading' appears more than once",
        ),
    ],
    ids=["empty", "header-only", "duplicate-column"],
)
def test_unusable_files_are_refused_by_every_command(capsys, tmp_path, models, data, words):
    for argv in commands(tmp_path, models, data).values():
        msg = refused(capsys, tmp_path, *argv)
        assert str(tmp_path / "in.csv") in msg and words in msg, msg


@pytest.mark.parametrize(
    "data,words",
    [
        ("point,ref_arcsec,reading\n0,0,1\n".encode("utf-16"), "UTF-16"),
        (
            "point,ref_arcsec,reading,note\n0,0,16,ok\n1,100,120,Temp 20\xb0C\n".encode("cp1252"),
            "line 3",
        ),
    ],
    ids=["utf-16", "windows-1252"],
)
def test_text_that_is_not_utf8_is_refused_naming_where(capsys, tmp_path, models, data, words):
    for argv in commands(tmp_path, models, data).values():
        msg = refused(capsys, tmp_path, *argv)
        assert str(tmp_path / "in.csv") in msg and words in msg and "UTF-8" in msg, msg


# --- output paths -----------------------------------------------------------------------------


def _all_commands(tmp_path, models, out):
    (tmp_path / "in.csv").write_text(SCALE)
    (tmp_path / "t.csv").write_text(TARGETS)
    return {
        "simulate": ["simulate", "--scenario", "seed003", "--out", out],
        "calibrate": [
            "calibrate",
            "--kind",
            "scale",
            "--method",
            "poly1",
            "--input",
            tmp_path / "in.csv",
            "--out",
            out,
        ],
        "correct": [
            "correct",
            "--model",
            models["scale"],
            "--input",
            tmp_path / "in.csv",
            "--out",
            out,
        ],
        "level": [
            "level",
            "--model",
            models["stage"],
            "--targets",
            tmp_path / "t.csv",
            "--out",
            out,
        ],
        "discrepancy": [
            "discrepancy",
            "--kind",
            "scale",
            "--input",
            tmp_path / "in.csv",
            "--out",
            out,
        ],
    }


@pytest.mark.parametrize(
    "where,words",
    [
        ("missing/out.x", "does not exist"),
        ("adir", "is a folder"),
        ("afile/out.x", "is not a folder"),
        ("", "output path is empty"),
    ],
)
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
        [
            "discrepancy",
            "--kind",
            "scale",
            "--input",
            data,
            "--out",
            tmp_path / "r.json",
            "--html",
            data,
        ],
        ["simulate", "--scenario", scenario, "--out", scenario],
    ]
    for argv in cases:
        msg = refused(capsys, tmp_path, *argv)
        assert "so the input is kept" in msg, msg
    assert {p: p.read_bytes() for p in before} == before


def test_discrepancy_with_an_unwritable_page_leaves_no_report(capsys, tmp_path, models):
    (tmp_path / "in.csv").write_text(SCALE)
    (tmp_path / "page").mkdir()
    refused(
        capsys,
        tmp_path,
        "discrepancy",
        "--kind",
        "scale",
        "--input",
        tmp_path / "in.csv",
        "--out",
        tmp_path / "r.json",
        "--html",
        tmp_path / "page",
    )
    (tmp_path / "r.html").mkdir()  # the default page path is a folder
    refused(
        capsys,
        tmp_path,
        "discrepancy",
        "--kind",
        "scale",
        "--input",
        tmp_path / "in.csv",
        "--out",
        tmp_path / "r.json",
    )


# --- options
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv,words",
    [
        (["simulate", "--scenario", "seed003"], "required: --out"),
        (
            ["simulate", "--scenario", "seed003", "--out", "{d}/o.csv", "--seed", "-1"],
            "a seed is a whole number >= 0",
        ),
        (
            ["simulate", "--scenario", "seed003", "--out", "{d}/o.csv", "--seed", "1.5"],
            "is not a whole number",
        ),
        (
            ["calibrate", "--kind", "bench", "--method", "poly1", "--input", "x", "--out", "y"],
            "invalid choice",
        ),
        (
            ["discrepancy", "--kind", "scale", "--input", "x", "--out", "y", "--sensor", "both"],
            "invalid choice",
        ),
    ],
)
def test_usage_errors_exit_2_on_one_line(capsys, tmp_path, argv, words):
    msg = refused(capsys, tmp_path, *[a.format(d=tmp_path) for a in argv])
    assert words in msg and "usage" not in msg, msg


# --- model and scenario files
# -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "edit,words",
    [
        (lambda t: t[: len(t) // 2], "not valid JSON"),
        (lambda t: "kind,method\nstage,homography\n", "not valid JSON"),
        (
            lambda t: json.dumps({**json.loads(t), "format_version": 2}),
            "format_version: 2 is not supported",
        ),
        (
            lambda t: json.dumps({**json.loads(t), "kind": "scale"}),
            "unknown method 'homography' for kind 'scale'",
        ),
        (lambda t: json.dumps([json.loads(t)]), "a model is a JSON object"),
    ],
    ids=["truncated", "not-json", "future-version", "other-kind", "not-an-object"],
)
def test_a_broken_model_file_is_named(capsys, tmp_path, models, edit, words):
    model = tmp_path / "m.json"
    model.write_text(edit(models["stage"].read_text()))
    (tmp_path / "in.csv").write_text(STAGE)
    (tmp_path / "t.csv").write_text(TARGETS)
    for argv in (
        ["correct", "--model", model, "--input", tmp_path / "in.csv", "--out", tmp_path / "o.csv"],
        ["level", "--model", model, "--targets", tmp_path / "t.csv", "--out", tmp_path / "o.csv"],
    ):
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
    msg = refused(
        capsys,
        tmp_path,
        "level",
        "--model",
        models["stage"],
        "--targets",
        tmp_path / "t.csv",
        "--out",
        tmp_path / "o.csv",
    )
    assert str(tmp_path / "t.csv") in msg, msg


@pytest.mark.parametrize(
    "scenario,field",
    [
        (
            {"kind": "scale", "grid": {"ref_arcsec": {"start": 0, "stop": 1e6, "step": 1e-6}}},
            "grid.ref_arcsec",
        ),
        (
            {
                "kind": "stage",
                "grid": {
                    "x_deg": {"start": -10, "stop": 10, "count": 100000},
                    "y_deg": {"start": -10, "stop": 10, "count": 100000},
                },
            },
            "grid",
        ),
        (
            {
                "kind": "turntable",
                "bench": {"beta_deg": 0, "m1": 1, "m2": 1},
                "grid": {
                    "azimuth_deg": {"start": 0, "stop": 359, "count": 100000},
                    "cycles": [{"north_arcsec": 0, "east_arcsec": 0}] * 11,
                },
            },
            "grid",
        ),
        ({"kind": "scale", "grid": "0..200"}, "grid"),
        ({"kind": "scale", "grid": {"ref_arcsec": [0], "repeats": 2.5}}, "grid.repeats"),
        (
            {"kind": "stage", "grid": {"x_deg": [0], "y_deg": [0]}, "effects": {"backlash": True}},
            "effects.backlash",
        ),
    ],
    ids=[
        "step-too-fine",
        "grid-too-large",
        "cycles-too-many",
        "grid-not-object",
        "repeats-fraction",
        "effect-not-object",
    ],
)
def test_a_scenario_with_wrong_values_is_refused_by_field_and_quickly(
    capsys, tmp_path, scenario, field
):
    sc = tmp_path / "sc.json"
    sc.write_text(json.dumps(scenario))
    msg = refused(capsys, tmp_path, "simulate", "--scenario", sc, "--out", tmp_path / "o.csv")
    assert f"{sc}: field {field}" in msg, msg


@pytest.mark.parametrize(
    "text,words",
    [
        ("[" * 100_000, "nested too deeply"),
        ('{"kind": "scale", "grid": ', "not valid JSON"),
        ("", "not valid JSON"),
    ],
    ids=["deep", "truncated", "empty"],
)
def test_a_scenario_file_that_is_not_json_is_refused(capsys, tmp_path, text, words):
    sc = tmp_path / "sc.json"
    sc.write_text(text)
    msg = refused(capsys, tmp_path, "simulate", "--scenario", sc, "--out", tmp_path / "o.csv")
    assert str(sc) in msg and words in msg, msg


def test_a_scenario_saved_with_a_byte_order_mark_is_accepted(capsys, tmp_path):
    sc = tmp_path / "sc.json"
    sc.write_text(
        "\ufeff" + json.dumps({"kind": "scale", "grid": {"ref_arcsec": [0, 100, 200]}}),
        encoding="utf-8",
    )
    rc, err = run(capsys, "simulate", "--scenario", sc, "--out", tmp_path / "o.csv")
    assert rc == 0, err
    assert read_dataset(tmp_path / "o.csv", "scale", ("ref_arcsec", "reading")).n_rows == 3


@pytest.mark.parametrize(
    "change, words",
    [
        (lambda m: m.update(columns=5), "field columns"),
        (lambda m: m.update(columns="abc"), "field columns"),
        (lambda m: m.update(kind=["scale"]), "field kind"),
        (lambda m: m.update(notes="a note"), "field notes"),
        (lambda m: m.update(options=[1]), "field options"),
        (lambda m: m.update(residuals=3), "field residuals"),
    ],
)
def test_a_model_file_with_a_field_of_the_wrong_type_is_refused_by_field(
    capsys, tmp_path, models, change, words
):
    model = json.loads(models["scale"].read_text())
    change(model)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(model))
    (tmp_path / "in.csv").write_text(SCALE)
    msg = refused(
        capsys,
        tmp_path,
        "correct",
        "--model",
        bad,
        "--input",
        tmp_path / "in.csv",
        "--out",
        tmp_path / "o.csv",
    )
    assert words in msg and "bad.json" in msg


def test_a_model_file_nested_too_deeply_is_refused(capsys, tmp_path):
    bad = tmp_path / "deep.json"
    bad.write_text("[" * 100_000 + "]" * 100_000)
    (tmp_path / "in.csv").write_text(SCALE)
    msg = refused(
        capsys,
        tmp_path,
        "correct",
        "--model",
        bad,
        "--input",
        tmp_path / "in.csv",
        "--out",
        tmp_path / "o.csv",
    )
    assert "deep.json" in msg


def test_a_model_file_saved_with_a_byte_order_mark_is_read(capsys, tmp_path, models):
    bom = tmp_path / "bom.json"
    bom.write_bytes(b"\xef\xbb\xbf" + models["scale"].read_bytes())
    (tmp_path / "in.csv").write_text(SCALE)
    rc, err = run(
        capsys,
        "correct",
        "--model",
        bom,
        "--input",
        tmp_path / "in.csv",
        "--out",
        tmp_path / "o.csv",
    )
    assert rc == 0, err
    assert "angle_arcsec" in (tmp_path / "o.csv").read_text().splitlines()[0]
