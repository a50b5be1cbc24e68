"""The command line starts at once: asking any command for its help loads none of the storage,
migrations, web app or heavy numerics that only some commands' work needs. Checked in a fresh
interpreter, command by command, through `sys.modules` (what was loaded, not how long it took)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

HEAVY = ("sqlalchemy", "alembic", "fastapi", "uvicorn", "scipy", "matplotlib")

# Runs every command's --help in one fresh interpreter and records, after each, which heavy
# packages had been loaded by then: the first command that loads one is the one at fault.
PROBE = textwrap.dedent("""
    import argparse, contextlib, io, json, sys
    heavy = set(sys.argv[1].split(","))
    from service.cli import build_parser, main

    def commands(parser, path=()):
        yield path
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, child in action.choices.items():
                    yield from commands(child, (*path, name))

    report = []
    for path in [()] + [p for p in commands(build_parser()) if p]:
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            try:
                main([*path, "--help"])
            except SystemExit:
                pass
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in heavy)
        command = " ".join(["tiltlab", *path, "--help"])
        report.append({"command": command, "printed": len(out.getvalue()), "loaded": loaded})
    print(json.dumps(report))
""")


def _help_of_every_command() -> list[dict]:
    done = subprocess.run(
        [sys.executable, "-c", PROBE, ",".join(HEAVY)],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return json.loads(done.stdout)


def test_help_of_every_command_loads_no_storage_web_app_or_heavy_numerics() -> None:
    report = _help_of_every_command()
    names = {r["command"] for r in report}
    for command in (
        "tiltlab --help",
        "tiltlab calibrate --help",
        "tiltlab serve --help",
        "tiltlab db --help",
        "tiltlab db upgrade --help",
        "tiltlab token create --help",
        "tiltlab discrepancy --help",
        "tiltlab verify-certificate --help",
    ):
        assert command in names
    for r in report:
        assert r["printed"] > 0, f"{r['command']} printed nothing"
        assert r["loaded"] == [], f"{r['command']} loaded {', '.join(r['loaded'])}"


def test_the_probe_sees_a_heavy_import() -> None:
    """The check above would notice: a command that does its work does load what it needs."""
    code = (
        "import sys; from service.cli import main; main(['db', 'history']); print('alembic' in "
        "sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.stdout.strip().endswith("True"), done.stderr
