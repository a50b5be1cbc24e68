"""A regular (non-editable) install carries every file the program reads at run time.

Checked twice: a wheel built from the repository, and one built from only what
docker/Dockerfile copies into its wheel stage (so the image cannot silently lose its migrations).
"""

import shlex
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def docker_build_context(dest: Path) -> Path:
    """The files the Dockerfile's wheel stage (its first) copies into its WORKDIR, laid out as it
    has them."""
    stages = 0
    for line in (ROOT / "docker" / "Dockerfile").read_text().splitlines():
        stages += line.startswith("FROM ")
        if stages > 1:  # the final stage installs the wheel the first one built
            break
        if not line.startswith("COPY "):  # other instructions may span lines or quote shell text
            continue
        words = shlex.split(line)
        if not words or words[0] != "COPY":
            continue
        *sources, target = [w for w in words[1:] if not w.startswith("--")]
        assert not target.startswith("/"), f"the wheel stage copies into its WORKDIR: {line}"
        for src in sources:
            origin = ROOT / src
            into = (
                dest / target / origin.name
                if target.endswith("/") or len(sources) > 1
                else dest / target
            )
            into.parent.mkdir(parents=True, exist_ok=True)
            if origin.is_dir():
                shutil.copytree(origin, into, ignore=shutil.ignore_patterns("__pycache__"))
            else:
                shutil.copy2(origin, into)
    return dest


@pytest.fixture(scope="module", params=["repository", "docker image"])
def wheel_names(request, tmp_path_factory):
    out = tmp_path_factory.mktemp("wheel")
    source = (
        ROOT
        if request.param == "repository"
        else docker_build_context(tmp_path_factory.mktemp("image"))
    )
    r = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(source)],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    (whl,) = out.glob("tiltlab-*.whl")
    return set(zipfile.ZipFile(whl).namelist())


def test_wheel_has_every_preset(wheel_names):
    presets = sorted(p.name for p in (ROOT / "service" / "scenarios" / "presets").glob("*.json"))
    assert presets and all(f"service/scenarios/presets/{p}" in wheel_names for p in presets)


def test_wheel_has_data_and_migrations(wheel_names):
    assert "service/calibration/data/seed003_table1.csv" in wheel_names
    assert (
        "service/migrations/env.py" in wheel_names
        and "service/migrations/script.py.mako" in wheel_names
    )
    versions = sorted(p.name for p in (ROOT / "migrations" / "versions").glob("*.py"))
    assert all(f"service/migrations/versions/{v}" in wheel_names for v in versions)


def test_wheel_has_every_python_module(wheel_names):
    src = {
        p.relative_to(ROOT).as_posix()
        for p in (ROOT / "service").rglob("*.py")
        if "__pycache__" not in p.parts
    }
    assert src <= wheel_names


def test_wheel_has_the_dashboard(wheel_names):
    web = sorted(p.name for p in (ROOT / "web").iterdir() if p.is_file())
    assert "index.html" in web and all(f"service/web/{w}" in wheel_names for w in web)


def test_wheel_has_the_certificate_schemas_and_their_licence(wheel_names):
    folder = ROOT / "service" / "lims" / "schemas" / "dcc-3.3.0"
    shipped = sorted(p.name for p in folder.iterdir() if p.is_file())
    assert {"dcc.xsd", "SI_Format.xsd", "README.md", "COPYING.LESSER"} <= set(shipped)
    assert all(f"service/lims/schemas/dcc-3.3.0/{name}" in wheel_names for name in shipped)
