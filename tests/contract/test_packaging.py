"""A regular (non-editable) install carries every file the program reads at run time."""

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def wheel_names(tmp_path_factory):
    out = tmp_path_factory.mktemp("wheel")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                        str(out), str(ROOT)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    (whl,) = out.glob("tiltlab-*.whl")
    return set(zipfile.ZipFile(whl).namelist())


def test_wheel_has_every_preset(wheel_names):
    presets = sorted(p.name for p in (ROOT / "service" / "scenarios" / "presets").glob("*.json"))
    assert presets and all(f"service/scenarios/presets/{p}" in wheel_names for p in presets)


def test_wheel_has_data_and_migrations(wheel_names):
    assert "service/calibration/data/seed003_table1.csv" in wheel_names
    assert "service/migrations/env.py" in wheel_names and "service/migrations/script.py.mako" in wheel_names
    versions = sorted(p.name for p in (ROOT / "migrations" / "versions").glob("*.py"))
    assert all(f"service/migrations/versions/{v}" in wheel_names for v in versions)


def test_wheel_has_every_python_module(wheel_names):
    src = {p.relative_to(ROOT).as_posix() for p in (ROOT / "service").rglob("*.py") if "__pycache__" not in p.parts}
    assert src <= wheel_names
