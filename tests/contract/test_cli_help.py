"""Help a lab engineer can work from: every option says what it is and its default (or that it
is required), every command shows an example, calibrate lists its methods per kind, `tiltlab`
alone prints the overview, and no help text points at documents the user does not have."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from service.calibration.registry import methods_for
from service.cli import build_parser, main
from service.commands._args import HelpFormatter


def _parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):  # type: ignore[no-untyped-def]
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _parsers(child, (*path, name))


ALL = list(_parsers(build_parser()))


def test_every_command_is_reached() -> None:
    names = {" ".join(p) for p, _ in ALL}
    for command in (
        "simulate",
        "calibrate",
        "correct",
        "level",
        "discrepancy",
        "reproduce",
        "serve",
        "db",
        "db downgrade",
        "db backup",
    ):
        assert command in names


@pytest.mark.parametrize("path,parser", ALL, ids=[" ".join(p) or "tiltlab" for p, _ in ALL])
def test_every_option_has_help_and_its_default(path, parser) -> None:  # type: ignore[no-untyped-def]
    formatter = HelpFormatter(prog="tiltlab")
    for action in parser._actions:
        if isinstance(
            action, (argparse._HelpAction, argparse._VersionAction, argparse._SubParsersAction)
        ):
            continue
        assert action.help, (path, action.dest)
        if action.option_strings:
            shown = formatter._get_help_string(action)
            assert "default" in shown or "(required)" in shown, (path, action.option_strings, shown)
    text = parser.format_help()
    if path:
        assert "example" in text and f"tiltlab {path[0]}" in text.split("example", 1)[1], path
    for foreign in ("spec/", "spec §", "../shared", "seeds/", "developer"):
        assert foreign not in text, (path, foreign)


def test_calibrate_lists_every_method_per_kind() -> None:
    text = dict((" ".join(p), q) for p, q in ALL)["calibrate"].format_help()
    listing = text.split("methods per kind:", 1)[1]
    for kind in ("stage", "rotation", "turntable"):
        for method in methods_for(kind):
            assert method in listing.split(f"{kind}:", 1)[1], (kind, method)
    assert "polyN" in listing.split("scale:", 1)[1]


def test_tiltlab_alone_prints_the_overview() -> None:
    r = subprocess.run(
        [sys.executable, "-m", "service"], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0, r.stderr
    assert "tiltlab calibrate" in r.stdout and "tiltlab serve" in r.stdout and "--help" in r.stdout


def test_simulate_list_names_the_presets(capsys) -> None:  # type: ignore[no-untyped-def]
    from service.scenarios import preset_names

    assert main(["simulate", "--list"]) == 0
    out = capsys.readouterr().out
    for name in preset_names():
        assert name in out


@pytest.mark.parametrize(
    "argv,words",
    [
        (
            ["calibrate", "--kind", "turntable", "--method", "reversal", "--rotation-deg", "nan"],
            ["NaN"],
        ),
        (
            ["calibrate", "--kind", "turntable", "--method", "reversal", "--rotation-deg", "inf"],
            ["infinite"],
        ),
        (["serve", "--database-wait-s", "nan"], ["NaN"]),
        (["sim", "--speed", "inf"], ["infinite"]),
    ],
)
def test_non_finite_numbers_are_named(argv, words, tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    argv = [
        *argv,
        *(
            ["--input", "x.csv", "--out", str(tmp_path / "m.json")]
            if argv[0] == "calibrate"
            else []
        ),
    ]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert all(w in err for w in words) and len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize(
    "command", ["simulate", "calibrate", "correct", "level", "discrepancy", "reproduce"]
)
def test_the_readme_summary_names_every_option(command) -> None:  # type: ignore[no-untyped-def]
    """The README's summary of the offline command line shows each command with all its options."""
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text(encoding="utf-8")
    section = readme.split("## The offline command line", 1)[1].split("\n## ", 1)[0]
    # the summary
    line = next(ln for ln in section.splitlines() if ln.strip().startswith(f"tiltlab {command} "))
    parser = dict((" ".join(p), q) for p, q in ALL)[command]
    options = [
        a.option_strings[-1]
        for a in parser._actions
        if a.option_strings and not isinstance(a, argparse._HelpAction)
    ]
    assert options and [o for o in options if o not in line] == [], line
