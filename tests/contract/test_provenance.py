"""Every artefact states where it came from: tiltlab version, UTC time, the command, and the
SHA-256 of each input file (MODEL.json, the discrepancy report and page, reproduce reports)."""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

from service import __version__
from service.cli import main


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _check(record: dict, command_word: str, inputs: dict[str, Path]) -> None:
    assert record["tiltlab_version"] == __version__
    when = dt.datetime.fromisoformat(record["utc"].replace("Z", "+00:00"))
    assert when.utcoffset() == dt.timedelta(0)
    assert record["command"].startswith("tiltlab ") and command_word in record["command"]
    for role, path in inputs.items():
        assert record["inputs"][role]["sha256"] == _sha(path), role


def test_model_and_discrepancy_report_carry_provenance(tmp_path: Path) -> None:
    data = tmp_path / "s3.csv"
    assert main(["simulate", "--scenario", "seed003", "--out", str(data)]) == 0
    model = tmp_path / "m.json"
    assert (
        main(
            [
                "calibrate",
                "--kind",
                "scale",
                "--method",
                "poly1",
                "--input",
                str(data),
                "--out",
                str(model),
            ]
        )
        == 0
    )
    _check(json.loads(model.read_text())["provenance"], "calibrate", {"input": data})
    report = tmp_path / "r.json"
    assert main(["discrepancy", "--kind", "scale", "--input", str(data), "--out", str(report)]) == 0
    record = json.loads(report.read_text())["provenance"]
    _check(record, "discrepancy", {"input": data})
    page = report.with_suffix(".html").read_text()
    assert "Provenance" in page and _sha(data) in page and __version__ in page


def test_model_provenance_survives_a_round_trip(tmp_path: Path) -> None:
    from service.io.model_files import read_model, write_model

    data = tmp_path / "s3.csv"
    assert main(["simulate", "--scenario", "seed003", "--out", str(data)]) == 0
    model = tmp_path / "m.json"
    assert (
        main(
            [
                "calibrate",
                "--kind",
                "scale",
                "--method",
                "poly1",
                "--input",
                str(data),
                "--out",
                str(model),
            ]
        )
        == 0
    )
    again = tmp_path / "again.json"
    write_model(again, read_model(model))
    assert (
        json.loads(again.read_text())["provenance"] == json.loads(model.read_text())["provenance"]
    )


def test_reproduce_report_carries_provenance(tmp_path: Path) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "service", "reproduce", "seed003", "--out-dir", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "MPLBACKEND": "Agg"},
    )
    assert r.returncode == 0, r.stderr
    text = (tmp_path / "seed003.md").read_text()
    section = text.split("## Provenance", 1)[1]
    assert f"tiltlab {__version__}" in section and "command: tiltlab reproduce seed003" in section
    import service.calibration.data as data

    table = Path(data.__file__).parent / "seed003_table1.csv"
    assert _sha(table) in section
