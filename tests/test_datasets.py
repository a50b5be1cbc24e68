"""Dataset files: strict validation with file, row and column, pass-through, atomic writes."""

import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.errors import InputError
from service.io import datasets
from service.io.datasets import read_dataset, write_dataset

STAGE_HEADER = "stage_x_deg,stage_y_deg,ref_x_deg,ref_y_deg,dir_x,t_s,note\n"


def _write(tmp_path, text, name="d.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _read(p, **kw):
    return read_dataset(
        p,
        "stage",
        ("stage_x_deg", "stage_y_deg", "ref_x_deg", "ref_y_deg"),
        ("dir_x", "t_s", "temp_c"),
        **kw,
    )


def test_reads_numbers_and_keeps_unknown_columns_as_text(tmp_path):
    p = _write(tmp_path, STAGE_HEADER + "1,2,1.01,2.02,1,0,first\n-3,4.5,-3,4.5,-1,10,second row\n")
    ds = _read(p)
    assert np.allclose(ds["stage_y_deg"], [2, 4.5]) and ds.text["note"] == ["first", "second row"]
    assert "note" in ds.passthrough()


@pytest.mark.parametrize(
    "row,col,cell,words",
    [
        (2, "ref_x_deg", "abc", "is not a number"),
        (1, "ref_y_deg", "", "empty cell"),
        (2, "stage_x_deg", "nan", "not a finite number"),
        (2, "stage_y_deg", "inf", "not a finite number"),
        (1, "stage_x_deg", "95", "outside [-90, 90]"),
        (2, "dir_x", "2", "not one of -1, 0, 1"),
        (2, "t_s", "-5", "earlier than the row before"),
    ],
)
def test_bad_cells_are_named_by_file_row_and_column(tmp_path, row, col, cell, words):
    rows = [["1", "2", "1", "2", "1", "0", "a"], ["3", "4", "3", "4", "-1", "10", "b"]]
    cols = STAGE_HEADER.strip().split(",")
    rows[row - 1][cols.index(col)] = cell
    p = _write(tmp_path, STAGE_HEADER + "".join(",".join(r) + "\n" for r in rows))
    with pytest.raises(InputError) as exc:
        _read(p)
    msg = str(exc.value)
    assert str(p) in msg and f"row {row}" in msg and repr(col) in msg and words in msg


def test_missing_required_column_is_named(tmp_path):
    p = _write(tmp_path, "stage_x_deg,stage_y_deg,ref_x_deg\n1,2,3\n")
    with pytest.raises(InputError, match="missing required column 'ref_y_deg'"):
        _read(p)


def test_alternative_columns(tmp_path):
    p = _write(tmp_path, "ref_deg,reading\n0,16\n0.1,378\n")
    ds = read_dataset(p, "scale", (("ref_arcsec", "ref_deg"), "reading"))
    assert "ref_deg" in ds.numeric
    with pytest.raises(InputError, match="'ref_arcsec' or 'ref_deg'"):
        read_dataset(
            _write(tmp_path, "reading\n1\n", "e.csv"),
            "scale",
            (("ref_arcsec", "ref_deg"), "reading"),
        )


def test_sines_have_a_small_margin_for_noise(tmp_path):
    ok = _write(tmp_path, "sx,sy\n1.0005,-1.0009\n")
    read_dataset(ok, "rotation", ("sx", "sy"))
    bad = _write(tmp_path, "sx,sy\n1.002,0\n", "bad.csv")
    with pytest.raises(InputError, match="row 1 .*'sx'.*outside"):
        read_dataset(bad, "rotation", ("sx", "sy"))


@pytest.mark.parametrize(
    "text,words",
    [
        ("", "empty file"),
        ("a,b\n", "no data rows"),
        ("a,a\n1,2\n", "appears more than once"),
        ("a,b\n1,2,3\n", "3 cells where the header has 2"),
    ],
)
def test_malformed_files(tmp_path, text, words):
    with pytest.raises(InputError, match=words):
        read_dataset(_write(tmp_path, text), "stage", ())


def test_no_file(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_dataset(tmp_path / "nope.csv", "stage", ())


def test_write_is_atomic_on_failure(tmp_path, monkeypatch):
    target = tmp_path / "out.csv"
    target.write_text("old content\n")

    calls = {"n": 0}
    real = datasets.format_value

    def failing(col, v):
        calls["n"] += 1
        if calls["n"] > 5:
            raise RuntimeError("disk full")
        return real(col, v)

    monkeypatch.setattr(datasets, "format_value", failing)
    with pytest.raises(RuntimeError):
        write_dataset(target, {"a": np.arange(100.0), "b": np.arange(100.0)})
    assert target.read_text() == "old content\n"
    assert os.listdir(tmp_path) == ["out.csv"]


def test_round_trip(tmp_path):
    p = tmp_path / "rt.csv"
    write_dataset(
        p,
        {
            "point": np.array([0, 1]),
            "stage_x_deg": np.array([0.1, -12.1234568]),
            "note": ["a", "b"],
        },
    )
    ds = read_dataset(p, "stage", ("stage_x_deg",))
    assert ds["stage_x_deg"][1] == -12.1234568 and ds.text["point"] == ["0", "1"]
    # degrees are written to 7 decimals (docs/models.md, "Digits"): more digits are not kept
    write_dataset(p, {"stage_x_deg": np.array([-12.123456789012])})
    assert read_dataset(p, "stage", ("stage_x_deg",))["stage_x_deg"][0] == -12.1234568


def test_written_file_has_the_umask_mode_not_a_private_one(tmp_path):
    old = os.umask(0o022)
    try:
        p = tmp_path / "shared.csv"
        write_dataset(p, {"a": np.arange(3.0)})
    finally:
        os.umask(old)
    assert (p.stat().st_mode & 0o777) == 0o644


@settings(
    max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    notes=st.lists(
        st.text(st.characters(blacklist_categories=("Cs",)), min_size=1, max_size=10),
        min_size=1,
        max_size=4,
    )
)
def test_pass_through_text_survives_a_write_and_a_read(tmp_path, notes):
    """Commas, quotes and line breaks (bare carriage returns too) come back; only the spaces and
    tabs around a cell go."""
    p = tmp_path / "t.csv"
    write_dataset(p, {"stage_x_deg": np.arange(float(len(notes))), "note": notes})
    assert read_dataset(p, "stage", ("stage_x_deg",)).text["note"] == [
        n.strip(" \t") for n in notes
    ]
