"""Every `tiltlab` command written in docs/, the README and the dashboard's help texts is one the
command line takes as written, and the ones a lab engineer runs at a desk run: a command shown with
an option the CLI does not have, or a name where it takes a positional argument, fails here.

A written command is taken from inline code and code blocks (continued lines joined). Its forms are
expanded: every alternative of `a|b|c` and every optional `[...]` part once, placeholders (NAME,
DATA.csv, MODEL.json ...) given real values. Each form is parsed by the CLI's own parser; the
offline commands (simulate, calibrate, correct, level, discrepancy, token, db) are then run in a
sandbox on a simulated run, the simulator with `devices` against it, and `serve` is started and
asked /health. `reproduce` (minutes of work, tests/contract/test_cli_reproduce_out_dir.py runs it)
and a server bound to a certificate's address are parsed only.
"""

from __future__ import annotations

import contextlib
import html
import io
import itertools
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.cli import build_parser
from tests.helpers.processes import spawn
from tests.helpers.running_service import free_port
from tests.helpers.waiting import eventually

ROOT = Path(__file__).resolve().parents[2]
# the installed command, as the docs run it (`python -m service` would find the sandbox's service/
# folder first)
TILTLAB = str(Path(sys.executable).parent / "tiltlab")
SOURCES = [*sorted((ROOT / "docs").glob("*.md")), ROOT / "README.md", ROOT / "web" / "index.html"]

# Placeholders as the docs write them, and what stands for them in the sandbox.
PLACEHOLDERS = {
    "KIND": "stage",
    "M": "kinematic",
    "METHOD": "kinematic",
    "NAME": "lims",
    "NAME_OR_FILE.json": "seed000",
    "DATA.csv": "data.csv",
    "points.csv": "data.csv",
    "MODEL.json": "model.json",
    "READINGS.csv": "data.csv",
    "OUT.csv": "out.csv",
    "TARGETS.csv": "targets.csv",
    "REPORT.json": "report.json",
    "PAGE.html": "page.html",
    "FILE": "bench.toml",
    "BENCH": "bench.toml",
    "DIR": "sim",
    "FOLDER": "reproduced",
    "REVISION": "head",
    "N": "4",
    "DEG": "0.001",
}
SPECIFIC = {  # a placeholder whose value depends on the option it follows
    ("--out", "FILE"): "backup.db",
    ("--scenario", "NAME_OR_FILE.json"): "seed000",
    # the bench a run came from: a scenario file's bench section
    ("--bench", "FILE"): "docs/examples/discrepancy/hidden_bench.json",
    ("--bench", "BENCH"): "docs/examples/discrepancy/hidden_bench.json",
    ("--bench", "NAME"): "sim-stage",  # a bench of a bench configuration: the simulator's
}


def written_commands(path: Path) -> list[str]:
    """The `tiltlab ...` commands of a document: inline code and code lines, continued lines
    joined."""
    text = path.read_text()
    if path.suffix == ".html":
        pieces = [html.unescape(m) for m in re.findall(r"<code>(.*?)</code>", text, re.S)]
    else:
        pieces = re.findall(r"`([^`\n]+)`", text)
        code, fenced = [], False
        for line in text.splitlines():
            if line.strip().startswith("```"):
                fenced = not fenced
            elif fenced or line.startswith("    "):
                code.append(line.strip())
        pieces += "\n".join(code).replace("\\\n", " ").splitlines()
    found = []
    for piece in pieces:
        piece = re.sub(r"^\$ ", "", piece.strip()).replace(".venv/bin/tiltlab", "tiltlab")
        if re.match(r"tiltlab [a-z][a-z-]*(?![:a-z-])", piece):
            found.append(" ".join(re.sub(r"\s+#.*$", "", piece).split()))
    return found


def forms(command: str) -> list[list[str]]:
    """Every form of a written command: the plain one, each optional part once, each alternative
    once."""
    # a remark in brackets, not an argument
    command = re.sub(r"\s\((?:--list|default)[^)]*\)", "", command)
    optional = re.findall(r"\[([^\]]+)\]", command)
    base = re.sub(r"\s*\[[^\]]+\]", "", command)
    variants = [base] + [f"{base} {part}" for part in optional]
    out = []
    for variant in variants:
        words = shlex.split(variant)
        choices = [
            word.split("|") if "|" in word and not word.startswith("-") else [word]
            for word in words
        ]
        for combo in itertools.product(*choices):
            out.append(list(combo))
    return out


# A synopsis for any kind, shown with an option of one kind, stands for that kind (its method, its
# data).
KIND_OF_OPTION = {"--rotation-deg": ("turntable", "reversal", "turntable.csv")}
DATA_OF_KIND = {"scale": "scale.csv", "turntable": "turntable.csv"}


def filled(words: list[str]) -> list[str]:
    values = dict(PLACEHOLDERS)
    for option, (kind, method, data) in KIND_OF_OPTION.items():
        if option in words:
            values.update(KIND=kind, METHOD=method, M=method, **{"DATA.csv": data})
    out = []
    for i, word in enumerate(words):
        previous = words[i - 1] if i else ""
        out.append(SPECIFIC.get((previous, word), values.get(word, word)))
    kind = out[out.index("--kind") + 1] if "--kind" in out else None
    if kind in DATA_OF_KIND and "--input" in out and out[out.index("--input") + 1] == "data.csv":
        out[out.index("--input") + 1] = DATA_OF_KIND[kind]
    return out


def is_mention(command: str) -> bool:
    """`tiltlab calibrate` (or `tiltlab correct --model`) in a sentence names a command (or its
    option); it is not a command line to run."""
    words = command.split()
    return len(words) == 2 or (
        len(words) == 3
        and (
            words[2].startswith("--")
            or words[1] in ("db", "token")
            and words[2]
            in (
                "create",
                "revoke",
                "list",
                "set-person",
                "upgrade",
                "verify",
                "current",
                "history",
                "backup",
            )
        )
    )


ALL = sorted({(command, source.name) for source in SOURCES for command in written_commands(source)})
RUNNABLE = sorted(
    {
        tuple(filled(form))
        for command, _ in ALL
        if not is_mention(command)
        for form in forms(command)
    }
)


def test_the_docs_write_commands():
    assert len(ALL) > 40 and len(RUNNABLE) > 40, (len(ALL), len(RUNNABLE))


@pytest.mark.parametrize(("command", "source"), ALL, ids=[f"{s}: {c}" for c, s in ALL])
def test_every_written_command_is_taken_by_the_cli(command: str, source: str) -> None:
    parser = build_parser()
    if is_mention(command):
        words = command.split()[1:]
        known = parser._subparsers._group_actions[0].choices  # type: ignore[union-attr]
        assert words[0] in known, f"{source}: `{command}` names no command of tiltlab"
        if len(words) == 2 and words[1].startswith("--"):
            options = {o for action in known[words[0]]._actions for o in action.option_strings}
            assert words[1] in options, (
                f"{source}: `{command}`: tiltlab {words[0]} has no option {words[1]}"
            )
        return
    for form in forms(command):
        argv = filled(form)[1:]
        errors = io.StringIO()
        with contextlib.redirect_stderr(errors), contextlib.redirect_stdout(io.StringIO()):
            try:
                parser.parse_args(argv)
            except SystemExit as exc:
                assert exc.code == 0, (
                    f"{source}: `{command}` as `tiltlab {' '.join(argv)}`: "
                    f"{errors.getvalue().strip()}"
                )


# ---------------------------------------------------------------- running them


@pytest.fixture(scope="module")
def sandbox(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with the files the docs' commands name: a simulated stage run, a model of it,
    targets."""
    here = tmp_path_factory.mktemp("docs-commands")
    shutil.copytree(ROOT / "docs" / "examples", here / "docs" / "examples")
    (here / "service" / "calibration" / "data").mkdir(parents=True)
    shutil.copy(
        ROOT / "service" / "calibration" / "data" / "seed003_table1.csv",
        here / "service" / "calibration" / "data",
    )
    run(here, ["simulate", "--scenario", "seed000", "--out", "data.csv"])
    run(here, ["simulate", "--scenario", "seed003", "--out", "scale.csv"])
    run(here, ["simulate", "--scenario", "seed004", "--out", "turntable.csv"])
    run(
        here,
        [
            "calibrate",
            "--kind",
            "stage",
            "--method",
            "kinematic",
            "--input",
            "data.csv",
            "--out",
            "model.json",
        ],
    )
    (here / "targets.csv").write_text("target_x_deg,target_y_deg\n0.5,-0.25\n1,1\n")
    (here / "data").mkdir()
    return here


def run(
    here: Path, argv: list[str], timeout: float = 300, data: str = "data"
) -> subprocess.CompletedProcess[str]:
    result = subprocess.run(
        [TILTLAB, *argv],
        cwd=here,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "TILTLAB_DATA_DIR": str(here / data)},
    )
    assert result.returncode == 0, (
        f"tiltlab {' '.join(argv)}: exit {result.returncode}: {result.stderr[-2000:]}"
    )
    return result


def _fresh_outputs(here: Path, argv: list[str]) -> None:
    """A command refuses to overwrite its output (by design): the previous form's output is removed
    first."""
    for option in ("--out", "--html"):
        if option in argv:
            target = here / argv[argv.index(option) + 1]
            if target.is_file() and target.name not in ("model.json", "data.csv"):
                target.unlink()
    if "--out" in argv and argv[argv.index("--out") + 1] in ("model.json", "data.csv"):
        argv[argv.index("--out") + 1] = "again-" + argv[argv.index("--out") + 1]
        (here / argv[argv.index("--out") + 1]).unlink(missing_ok=True)


OFFLINE = ("simulate", "calibrate", "correct", "level", "plan", "discrepancy", "token", "db")
OFFLINE_FORMS = [
    form
    for form in RUNNABLE
    if form[1] in OFFLINE
    and not (form[1] == "db" and form[2] == "downgrade")
    and "--adopt" not in form
]


@pytest.mark.slow
@pytest.mark.parametrize("form", OFFLINE_FORMS, ids=[" ".join(f) for f in OFFLINE_FORMS])
def test_every_offline_command_runs(sandbox: Path, form: tuple[str, ...]) -> None:
    argv = list(form[1:])
    _fresh_outputs(sandbox, argv)
    data = "data"
    if argv[0] in ("token", "db"):  # a data directory of its own, with its database
        data = f"data-{abs(hash(form))}"
        shutil.rmtree(sandbox / data, ignore_errors=True)
        run(sandbox, ["db", "upgrade"], data=data)
    # the token the command names exists
    if argv[:2] in (["token", "revoke"], ["token", "set-person"]):
        run(sandbox, ["token", "create", "--name", argv[2], "--scopes", "read"], data=data)
    run(sandbox, argv, data=data)


@contextlib.contextmanager
def simulator(here: Path, folder: str, *extra: str) -> Iterator[Path]:
    proc = spawn(
        [TILTLAB, "sim", "--dir", folder, *extra],
        cwd=here,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    config = here / folder / "bench.toml"

    def written() -> bool:
        if config.exists():
            return True
        assert proc.poll() is None, proc.stdout.read() if proc.stdout else ""
        return False

    try:
        eventually(written, timeout_s=60, every_s=0.2, what=f"the simulator writing {config}")
        yield config
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.mark.slow
def test_the_simulator_the_devices_check_and_the_service_run_as_written(sandbox: Path) -> None:
    """`tiltlab sim`, `tiltlab devices --config` against it, `tiltlab serve --bench-config` on it
    and `tiltlab serve --sim-speed 5`: each started as written, answering, then stopped."""
    sims = [form for form in RUNNABLE if form[1] == "sim"]
    assert sims
    with simulator(sandbox, "sim") as config:
        shutil.copy(config, sandbox / "bench.toml")
        for form in [f for f in RUNNABLE if f[1] == "devices"]:
            run(sandbox, in_sandbox(form[1:]), timeout=120)
        for form in [
            f
            for f in RUNNABLE
            if f[1] == "serve" and "--ssl-certfile" not in f and "--host" not in f
        ]:
            _serves(sandbox, in_sandbox(form[1:]))


def in_sandbox(argv: tuple[str, ...]) -> list[str]:
    """The docs' example folder of the simulator (/tmp/bench) is the sandbox's: the machine is
    shared."""
    return [re.sub(r"^/tmp/(bench|rot)\b", "sim", word) for word in argv]


def _serves(here: Path, argv: list[str]) -> None:
    port = free_port()
    data = here / f"serve-{port}"
    proc = spawn(
        [TILTLAB, *argv, "--port", str(port)],
        cwd=here,
        env={**os.environ, "TILTLAB_DATA_DIR": str(data)},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )

    def answers() -> bool:
        try:
            health = httpx.get(f"http://127.0.0.1:{port}/health", timeout=2)
        except httpx.TransportError:
            assert proc.poll() is None, (
                f"tiltlab {' '.join(argv)}: {proc.stdout.read() if proc.stdout else ''}"
            )
            return False
        assert health.status_code == 200, health.text
        return True

    try:
        eventually(answers, timeout_s=60, every_s=0.3, what=f"tiltlab {' '.join(argv)} answering")
    finally:
        proc.terminate()
        proc.wait(timeout=20)
