"""`tiltlab reproduce` writes into a new folder unless told otherwise, and refuses an unusable
--out-dir on one line with exit 2 (run as a user runs it, from a working folder)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


def _reproduce(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "MPLBACKEND": "Agg"}
    return subprocess.run(
        [sys.executable, "-m", "service", "reproduce", "seed003", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_default_is_a_new_folder(tmp_path: Path) -> None:
    kept = tmp_path / "docs" / "reproduce"
    kept.mkdir(parents=True)
    (kept / "seed003.md").write_text("kept\n")
    r = _reproduce(tmp_path)
    assert r.returncode == 0, r.stderr
    made = [p for p in tmp_path.iterdir() if p.name.startswith("tiltlab-reproduce-")]
    assert len(made) == 1 and (made[0] / "seed003.md").is_file()
    assert (kept / "seed003.md").read_text() == "kept\n"
    assert str(made[0].name) in r.stderr


def test_unusable_out_dir_is_one_line_exit_2(tmp_path: Path) -> None:
    (tmp_path / "afile").write_text("x")
    for bad in ("afile", "afile/sub", ""):
        r = _reproduce(tmp_path, "--out-dir", bad)
        assert r.returncode == 2, (bad, r.stderr)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and "--out-dir" in lines[0] and "Traceback" not in r.stderr, (
            bad,
            r.stderr,
        )
    assert (tmp_path / "afile").read_text() == "x"
