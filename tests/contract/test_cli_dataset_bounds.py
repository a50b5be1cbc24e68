"""`tiltlab calibrate` on datasets it must not take quietly: a sensor with one axis column (an error
naming the missing one, not a silent fit without the sensor), and a million rows (refused before
they are read, in bounded memory, naming --max-rows; a run has a row per settled point)."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

CLI = [sys.executable, "-m", "service"]


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[str], list[list[str]]]:
    folder = tmp_path_factory.mktemp("run")
    r = subprocess.run(
        [*CLI, "simulate", "--scenario", "seed000", "--out", str(folder / "run.csv")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    rows = list(csv.reader((folder / "run.csv").open()))
    return rows[0], rows[1:]


def _write(
    path: Path, header: list[str], body: list[list[str]], keep: list[str], n: int | None = None
) -> Path:
    idx = [header.index(c) for c in keep]
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(keep)
        for i in range(len(body) if n is None else n):
            w.writerow([body[i % len(body)][j] for j in idx])
    return path


# The command run as `python -m service`, then its own peak memory (VmHWM: since its exec, not the
# forking test process's) on the last line of stderr.
PEAK = (
    "import runpy, sys\nsys.argv = ['tiltlab', *sys.argv[1:]]\ntry:\n    "
    "runpy.run_module('service', run_name='__main__')\nfinally:\n    print([l for l in "
    "open('/proc/self/status') if l.startswith('VmHWM')][0].split()[1], file=sys.stderr)\n"
)


def _calibrate(path: Path, out: Path, *extra: str) -> tuple[int, str, int]:
    """(exit code, stderr, peak memory of the process in kB)."""
    r = subprocess.run(
        [
            sys.executable,
            "-c",
            PEAK,
            "calibrate",
            "--kind",
            "stage",
            "--method",
            "homography",
            "--input",
            str(path),
            "--out",
            str(out),
            *extra,
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    *said, peak = r.stderr.strip().splitlines()
    return r.returncode, "\n".join(said), int(peak)


@pytest.mark.parametrize("missing", ["meas_y_deg", "meas_x_deg"])
def test_one_axis_of_a_sensor_is_an_error_naming_the_other(
    run, tmp_path: Path, missing: str
) -> None:
    header, body = run
    keep = [c for c in header if c not in (missing, "t_s")]
    code, err, _ = _calibrate(
        _write(tmp_path / "half.csv", header, body, keep), tmp_path / "model.json"
    )
    assert code == 2 and f"not {missing!r}" in err, err
    assert not (tmp_path / "model.json").exists()


def test_a_million_rows_are_refused_before_they_are_read(run, tmp_path: Path) -> None:
    header, body = run
    keep = [c for c in header if c != "t_s"]  # (times would run backwards where the rows repeat)
    big = _write(tmp_path / "big.csv", header, body, keep, n=1_000_000)
    code, err, peak_kb = _calibrate(big, tmp_path / "model.json")
    assert code == 2 and "more than 100,000 data rows" in err and "--max-rows" in err, err
    # the file is 60 MB; reading it whole took GBs
    assert peak_kb < 200 * 1024, f"{peak_kb} kB to refuse it"
    assert not (tmp_path / "model.json").exists()


def test_max_rows_sets_the_limit(run, tmp_path: Path) -> None:
    header, body = run
    keep = [c for c in header if c != "t_s"]
    data = _write(tmp_path / "run.csv", header, body, keep, n=150)
    code, err, _ = _calibrate(data, tmp_path / "model.json", "--max-rows", "100")
    assert code == 2 and "more than 100 data rows" in err, err
    code, err, _ = _calibrate(data, tmp_path / "model.json", "--max-rows", "150")
    assert code == 0, err
    assert (tmp_path / "model.json").exists()
