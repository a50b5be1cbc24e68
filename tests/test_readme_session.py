"""The README's `curl` session, run word for word: its commands are taken from README.md and run by
bash in a fresh folder against a daemon this test starts as the README's paragraph says (`tiltlab
serve` with the options the paragraph gives: a bench with a worm error to find, sped up), with
`tiltlab` found the way the session finds it (`source .venv/bin/activate`)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.running_service import running_service

ROOT = Path(__file__).resolve().parents[1]
VENV = Path(sys.prefix)


def session_paragraph() -> str:
    """The README's "A session with `curl`" paragraph, joined into one line."""
    lines = (ROOT / "README.md").read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("A session with `curl`"))
    end = next(i for i in range(start, len(lines)) if not lines[i].strip())
    return " ".join(lines[start:end])


def serve_options() -> list[str]:
    """The options the paragraph starts the daemon with (`.venv/bin/tiltlab serve ...`)."""
    found = re.search(r"`\.venv/bin/tiltlab serve ([^`]*)`", session_paragraph())
    assert found, session_paragraph()
    return found.group(1).split()


def session_commands() -> str:
    """The indented block that follows the README's "A session with `curl`" paragraph."""
    lines = (ROOT / "README.md").read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("A session with `curl`"))
    i = start
    while lines[i].strip():  # the paragraph
        i += 1
    block: list[str] = []
    for line in lines[i + 1 :]:
        if line and not line.startswith("    "):
            break
        block.append(line[4:])
    assert any("curl" in b for b in block), block
    return "\n".join(block).strip() + "\n"


@pytest.mark.skipif(
    not (VENV / "bin" / "activate").exists(),
    reason="runs from a virtual environment, as the README",
)
@pytest.mark.skipif(shutil.which("curl") is None, reason="the session uses curl")
def test_readme_curl_session_runs_as_written(tmp_path: Path) -> None:
    script = session_commands()
    assert "tiltlab serve" not in script, "the session must not start a second daemon"
    work = tmp_path / "clone"
    work.mkdir()
    (work / ".venv").symlink_to(VENV)  # the clone's .venv, made by the README's first command
    data = tmp_path / "data"
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "TILTLAB_CONFIG")}
    # tiltlab is not on the PATH until the session activates the virtual environment
    env["PATH"] = os.pathsep.join(
        p for p in env.get("PATH", "").split(os.pathsep) if not p.startswith(str(VENV))
    )
    options = serve_options()
    assert "--scenario" in options and "--sim-speed" in options, options
    # tiltlab serve as the paragraph says, on a free port
    with running_service(data, args=options) as base:
        env.update(TILTLAB_DATA_DIR=str(data), TILTLAB_PORT=base.rsplit(":", 1)[1])
        run = subprocess.run(
            ["bash", "-e", "-c", script],
            cwd=work,
            env=env,
            capture_output=True,
            text=True,
            timeout=900,
        )
    assert run.returncode == 0, (run.stdout[-3000:], run.stderr[-3000:])
    out = run.stdout
    assert "HTTP/1.1 202" in out and "location: /calibrations/1" in out.lower(), out[:2000]
    assert '"state":"succeeded"' in out, out[-3000:]
    assert out.count('"within_tolerance":true') == 2, out[-3000:]
    # the bench hides a worm error: the diagnosis names it, the plan lists what the points cannot
    # test, the adopt step makes record 2
    # the 202's (none yet), the finished one's, the plan's
    named = re.findall(r'"named_effects":\[([^]]*)\]', out)
    assert named[0] == "" and '"periodic_error"' in named[1] and '"adoptable":true' in out, out[
        -6000:
    ]
    assert '"plan":{' in out and '"effect":"backlash"' in out, out[-6000:]
    assert "HTTP/1.1 201" in out and "location: /records/2" in out.lower(), out[-3000:]
    model = json.loads((work / "MODEL.json").read_text())
    again = json.loads((work / "again.json").read_text())
    assert (work / "points.csv").read_text().startswith("point,")
    # "same parameters": the command line refits the downloaded points to the record's values
    for name, value in model["parameters"].items():
        assert again["parameters"][name]["value"] == pytest.approx(
            value["value"], rel=1e-6, abs=1e-9
        ), name
    assert not re.search(r"command not found", run.stderr), run.stderr
