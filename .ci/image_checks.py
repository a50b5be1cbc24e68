"""The image and docker/compose.yaml exercised on the engine .ci/image started (standard library
only).

The image alone: /health, the admin token file (0600, never in the container's log), the user and
group it runs as and that own /data, a calibration through the API, a restart that keeps the data
and resumes a job it interrupted, its health status while it serves on --port 9000 read-only with
every capability dropped, the installed packages against requirements.lock, the entry point's
commands. compose.yaml: the fleet profile started from nothing several times (two daemons, both
benches through either, no crash, one admin token in the one shared place), then the single profile.
Containers use host networking on free ports and listen on 127.0.0.1 only.
"""

from __future__ import annotations

import argparse
import json
import operator
import os
import re
import secrets
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

ROOT = Path(__file__).resolve().parents[1]
PROJECT = "tiltlabci"
FLEET_ROUNDS = (
    2  # the start-together race is met again in each (the suite repeats it more: tests/fleet)
)
T = TypeVar("T")


class CheckFailed(AssertionError):
    pass


def say(text: str) -> None:
    print(f"ci/image: {text}", file=sys.stderr, flush=True)


def require(condition: object, what: str) -> None:
    if not condition:
        raise CheckFailed(what)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def eventually(
    what: str,
    probe: Callable[[], T],
    ok: Callable[[T], bool],
    timeout_s: float,
    every_s: float = 1.0,
) -> T:
    deadline = time.monotonic() + timeout_s
    last: object = None
    while time.monotonic() < deadline:
        try:
            value = probe()
            if ok(value):
                return value
            last = value
        except (OSError, urllib.error.URLError, CheckFailed) as exc:
            last = exc
        time.sleep(every_s)
    raise CheckFailed(f"{what}: not within {timeout_s:g} s; last: {str(last)[:600]}")


@dataclass
class Answer:
    status: int
    body: Any


def http(
    method: str, url: str, token: str | None = None, body: Any = None, timeout_s: float = 30
) -> Answer:
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(url, data=data, method=method)
    if token:
        request.add_header("Authorization", f"Bearer {token}")
    if data is not None:
        request.add_header("Content-Type", "application/json")
    try:
        with urllib.request.urlopen(request, timeout=timeout_s) as answer:
            status, raw = answer.status, answer.read()
    except urllib.error.HTTPError as exc:
        status, raw = exc.code, exc.read()
    try:
        return Answer(status, json.loads(raw))
    except ValueError:
        return Answer(status, raw.decode(errors="replace"))


class Engine:
    def __init__(self, docker: str, compose: str, work: Path) -> None:
        self.docker_bin, self.compose_bin, self.work = docker, compose, work

    def docker(self, *args: str, check: bool = True, timeout_s: float = 300) -> str:
        r = subprocess.run(
            [self.docker_bin, *args], capture_output=True, text=True, timeout=timeout_s
        )
        if check and r.returncode != 0:
            raise CheckFailed(
                f"docker {' '.join(args)}: exit {r.returncode}: "
                f"{(r.stderr or r.stdout).strip()[-800:]}"
            )
        return r.stdout

    def compose(self, *args: str, env: dict[str, str], timeout_s: float = 600) -> str:
        return self.compose_file(
            "compose.yaml", "-f", "ci-host-network.yaml", *args, env=env, timeout_s=timeout_s
        )

    def compose_file(
        self, file: str, *args: str, env: dict[str, str], timeout_s: float = 600
    ) -> str:
        r = subprocess.run(
            [self.compose_bin, "-p", PROJECT, "-f", file, *args],
            cwd=self.work / "compose",
            capture_output=True,
            text=True,
            timeout=timeout_s,
            env={**os.environ, **env},
        )
        if r.returncode != 0:
            raise CheckFailed(
                f"docker-compose {' '.join(args)}: exit {r.returncode}: "
                f"{(r.stderr or r.stdout).strip()[-1500:]}"
            )
        return r.stdout + r.stderr

    def inspect(self, container: str) -> dict[str, Any]:
        return dict(json.loads(self.docker("inspect", container))[0])

    def logs(self, container: str) -> str:
        r = subprocess.run(
            [self.docker_bin, "logs", container], capture_output=True, text=True, timeout=60
        )
        return r.stdout + r.stderr


def wait_health(base: str, what: str, timeout_s: float = 180) -> dict[str, Any]:
    answer = eventually(
        f"{what} answers /health",
        lambda: http("GET", f"{base}/health", timeout_s=5),
        lambda a: a.status == 200,
        timeout_s,
    )
    return dict(answer.body)


def wait_job(
    base: str, token: str, job_id: int, states: tuple[str, ...], timeout_s: float = 300
) -> dict[str, Any]:
    answer = eventually(
        f"job {job_id} reaches {'/'.join(states)}",
        lambda: http("GET", f"{base}/calibrations/{job_id}", token),
        lambda a: a.status == 200 and a.body["state"] in states,
        timeout_s,
    )
    return dict(answer.body)


def start_calibration(base: str, token: str, n: int) -> int:
    answer = http(
        "POST",
        f"{base}/calibrations",
        token,
        {
            "procedure": "stage-grid",
            "method": "kinematic",
            "grid": {"x_deg": [-4, 4], "y_deg": [-4, 4], "n_x": n, "n_y": n},
        },
    )
    require(answer.status == 202, f"POST /calibrations: {answer.status} {answer.body}")
    return int(answer.body["id"])


# ------------------------------------------------------------------ the image alone


def image_alone(engine: Engine, image: str) -> None:
    # --port 9000 while TILTLAB_PORT says 8000, read-only, every capability dropped: the health
    # check follows the daemon. No network but its own loopback, so port 9000 of this machine is not
    # touched.
    engine.docker(
        "run",
        "-d",
        "--name",
        "tl-port-9000",
        "--network",
        "none",
        "--read-only",
        "--cap-drop",
        "ALL",
        "--security-opt",
        "no-new-privileges",
        "-v",
        "tl-port-9000-data:/data",
        image,
        "--port",
        "9000",
    )
    started_9000 = time.monotonic()

    port = free_port()
    base = f"http://127.0.0.1:{port}"
    engine.docker(
        "run",
        "-d",
        "--name",
        "tl-alone",
        "--network",
        "host",
        "-v",
        "tl-alone-data:/data",
        "-e",
        "TILTLAB_HOST=127.0.0.1",
        "-e",
        "TILTLAB_SIM_SPEED=20",
        image,
        "--port",
        str(port),
    )
    health = wait_health(base, "the image alone")
    require(health["database"] == "sqlite:////data/tiltlab.db", f"SQLite in /data: {health}")
    say(
        f"image alone: /health 200 on --port {port} ({health['database']}, benches "
        f"{health['benches']})"
    )

    token = engine.docker("exec", "tl-alone", "cat", "/data/admin.token").strip()
    mode = engine.docker("exec", "tl-alone", "stat", "-c", "%a %U:%G", "/data/admin.token").strip()
    require(mode == "600 tiltlab:tiltlab", f"admin.token mode and owner: {mode}")
    log = engine.logs("tl-alone")
    require(token not in log, "the admin token appears in docker logs")
    require(
        "admin token written to /data/admin.token (mode 0600)" in log
        and "(token: the admin token in /data/admin.token)" in log,
        f"the start names the token file: {log[-800:]}",
    )
    say(
        "image alone: admin token in /data/admin.token, mode 600, owner tiltlab:tiltlab; not in "
        "docker logs"
    )

    who = engine.docker("exec", "tl-alone", "id").strip()
    require(who == "uid=10001(tiltlab) gid=10001(tiltlab) groups=10001(tiltlab)", f"id: {who}")
    owner = engine.docker("exec", "tl-alone", "stat", "-c", "%U:%G %a", "/data").strip()
    require(owner == "tiltlab:tiltlab 750", f"/data: {owner}")
    say(f"image alone: id: {who}; /data owned {owner}")

    first = start_calibration(base, token, 3)
    job = wait_job(base, token, first, ("succeeded", "failed", "cancelled"))
    require(job["state"] == "succeeded", f"calibration {first}: {job}")
    record_id = job["record"]["id"]
    record = http("GET", f"{base}/records/{record_id}", token).body
    say(f"image alone: calibration {first} through the API succeeded, record {record_id}")

    second = start_calibration(base, token, 5)
    eventually(
        f"job {second} measures",
        lambda: http("GET", f"{base}/calibrations/{second}", token).body,
        lambda j: j["state"] == "running" and j["progress"]["points_done"] >= 2,
        300,
        every_s=0.5,
    )
    engine.docker("restart", "-t", "30", "tl-alone")
    wait_health(base, "the image after a restart")
    job = http("GET", f"{base}/calibrations/{second}", token).body
    require(
        job["state"] == "failed" and job["interrupted"] is True,
        f"job {second} after the restart: {job}",
    )
    done_at_restart, planned = job["progress"]["points_done"], job["progress"]["points_total"]
    kept = http("GET", f"{base}/records/{record_id}", token)
    require(
        kept.status == 200 and kept.body["content_sha256"] == record["content_sha256"],
        f"record {record_id} after the restart: {kept.status} {kept.body}",
    )
    resumed = http("POST", f"{base}/calibrations/{second}/resume", token)
    require(resumed.status in (200, 202), f"resume {second}: {resumed.status} {resumed.body}")
    job = wait_job(base, token, second, ("succeeded", "failed", "cancelled"))
    require(job["state"] == "succeeded", f"resumed calibration {second}: {job}")
    say(
        f"image alone: restart kept token and record {record_id}; calibration {second} ({planned} "
        "points), interrupted"
        f" by it after {done_at_restart}, resumed and succeeded (record {job['record']['id']})"
    )

    listing = engine.docker(
        "exec",
        "tl-alone",
        "sh",
        "-c",
        "ls -A /; python -c 'import service; print(service.__file__)'",
    ).split()
    require("app" not in listing, f"/ holds /app: {listing}")
    require(
        any(re.search(r"/(site|dist)-packages/service/__init__\.py$", w) for w in listing),
        f"tiltlab is installed as a package: {listing}",
    )
    require(
        engine.docker("run", "--rm", "--network", "none", image, "sh", "-c", "echo from-sh").strip()
        == "from-sh",
        "`docker run IMAGE sh -c ...` runs sh",
    )
    current = engine.docker("run", "--rm", "--network", "none", image, "db", "current")
    require("revision" in current, f"`docker run IMAGE db current`: {current}")
    usage = engine.docker("run", "--rm", "--network", "none", image, "--help")
    require(usage.startswith("usage: tiltlab serve"), f"`docker run IMAGE --help`: {usage[:200]}")
    say(
        "image alone: no /app, tiltlab installed as a package; `sh`, `db current` and `--help` "
        "reach what they name"
    )

    packages_equal_the_lock(engine, image)

    state = eventually(
        "the --port 9000 container turns healthy",
        lambda: engine.inspect("tl-port-9000")["State"],
        lambda s: s["Health"]["Status"] in ("healthy", "unhealthy") or not s["Running"],
        240,
        every_s=2,
    )
    probes = [entry["Output"].strip() for entry in state.get("Health", {}).get("Log", [])]
    require(state["Running"] and state["Health"]["Status"] == "healthy", f"--port 9000: {state}")
    require(
        any(":9000/health: 200" in p for p in probes),
        f"the health check probed port 9000: {probes}",
    )
    say(
        "image with --port 9000 (read-only, --cap-drop ALL): docker inspect health "
        f"{state['Health']['Status']} "
        f"after {time.monotonic() - started_9000:.0f} s; probe: {probes[-1]}"
    )
    for name in ("tl-alone", "tl-port-9000"):
        engine.docker("rm", "-f", "-v", name)
    engine.docker("volume", "rm", "tl-alone-data", "tl-port-9000-data")


def _lock() -> dict[str, str]:
    pins: dict[str, str] = {}
    for line in (ROOT / "requirements.lock").read_text().splitlines():
        m = re.match(r"^([A-Za-z0-9_.-]+)==(\S+)", line)
        if m:
            pins[_canonical(m.group(1))] = m.group(2)
    return pins


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


INSTALLERS = {"pip", "setuptools", "wheel"}  # the base image's installer, which pip itself needs


def packages_equal_the_lock(engine: Engine, image: str) -> None:
    """Every distribution in the image is at the version requirements.lock pins; tiltlab's own
    requirements (and the postgres extra) are all there, so pip's resolution made the rest."""
    program = (
        "import importlib.metadata as m, json; print(json.dumps({'installed': "
        "{d.metadata['Name']: d.version for d in m.distributions()}, 'requires': "
        "m.requires('tiltlab')}))"
    )
    found = json.loads(
        engine.docker("run", "--rm", "--network", "none", image, "python", "-c", program)
    )
    installed = {_canonical(name): version for name, version in found["installed"].items()}
    lock = _lock()
    ours = {
        name: version for name, version in installed.items() if name not in INSTALLERS | {"tiltlab"}
    }
    differ = {
        name: (version, lock.get(name))
        for name, version in ours.items()
        if lock.get(name) != version
    }
    require(
        not differ,
        f"packages in the image that differ from requirements.lock (image, lock): {differ}",
    )
    needed = set()
    for requirement in found["requires"]:
        name = _canonical(re.split(r"[<>=!~;\[ ]", requirement, maxsplit=1)[0])
        marker = requirement.partition(";")[2]
        if "extra" in marker and "postgres" not in marker:
            continue  # another extra (dev): not in the image
        needed.add(name)
    missing = sorted(n for n in needed if n not in installed)
    require(not missing, f"tiltlab's requirements missing from the image: {missing}")
    check = engine.docker(
        "run", "--rm", "--network", "none", image, "python", "-m", "pip", "check", check=False
    )
    require("No broken requirements found" in check, f"pip check in the image: {check}")
    tools = ", ".join(f"{n} {installed[n]}" for n in sorted(INSTALLERS & set(installed)))
    say(
        f"image packages: {len(ours)} besides tiltlab and the installer ({tools}), every one at "
        f"requirements.lock's version, 0 differ; tiltlab's {len(needed)} requirements with the "
        "postgres extra all there; pip check clean"
    )


# ------------------------------------------------------------------ compose.yaml


@dataclass
class Ports:
    postgres: int
    nats: int
    nats_monitor: int
    single: int
    bench_1: int
    bench_2: int


def prepare_compose(work: Path) -> tuple[Ports, str]:
    """compose.yaml as it is, its env file, and an override that moves every service onto the host's
    network at free ports on 127.0.0.1 (this engine makes no bridge)."""
    folder = work / "compose"
    folder.mkdir()
    # The one change to the copy: its published ports go (they need the bridge this engine does not
    # make, and Compose refuses them beside host networking); each service listens on a free port
    # instead.
    original = (ROOT / "docker" / "compose.yaml").read_text()
    copy, dropped = re.subn(r"(?m)^ +ports: \[[^\]\n]*\]\n", "", original)
    require(
        dropped == 3 and not re.search(r"(?m)^ +ports:", copy),
        f"compose.yaml's ports lines: {dropped} found",
    )
    (folder / "compose.yaml").write_text(copy)
    (folder / "compose.published.yaml").write_text(original)
    password = secrets.token_hex(12)
    example = (ROOT / "docker" / "tiltlab.env.example").read_text()
    (folder / "tiltlab.env").write_text(example.replace("change-me", password))
    ports = Ports(*(free_port() for _ in range(6)))
    database = f"postgresql+psycopg://tiltlab:{password}@127.0.0.1:{ports.postgres}/tiltlab"
    broker = f"nats://127.0.0.1:{ports.nats}"

    def daemon(port: int, *fleet: str) -> dict[str, Any]:
        env = {
            "TILTLAB_HOST": "127.0.0.1",
            "TILTLAB_PORT": str(port),
            "TILTLAB_DATABASE_URL": database,
            "TILTLAB_SIM_SPEED": "20",
        }
        if fleet:
            env["TILTLAB_BROKER_URL"] = broker
        return {"network_mode": "host", "environment": env}

    override = {
        "services": {
            "db": {
                "network_mode": "host",
                "environment": {"PGPORT": str(ports.postgres)},
                "command": ["postgres", "-c", "listen_addresses=127.0.0.1"],
            },
            "nats": {
                "network_mode": "host",
                "command": [
                    "-js",
                    "-sd",
                    "/data",
                    "-a",
                    "127.0.0.1",
                    "-p",
                    str(ports.nats),
                    "-m",
                    str(ports.nats_monitor),
                ],
                "healthcheck": {
                    "test": [
                        "CMD",
                        "wget",
                        "-q",
                        "-O",
                        "-",
                        f"http://127.0.0.1:{ports.nats_monitor}/healthz?js-enabled-only=true",
                    ]
                },
            },
            "tiltlab": daemon(ports.single),
            "bench-1": daemon(ports.bench_1, "fleet"),
            "bench-2": daemon(ports.bench_2, "fleet"),
        }
    }
    (folder / "ci-host-network.yaml").write_text(json.dumps(override, indent=2))  # JSON is YAML
    return ports, password


def project_containers(engine: Engine) -> dict[str, str]:
    """service -> container name, of this project's containers."""
    out = engine.docker(
        "ps",
        "-a",
        "--filter",
        f"label=com.docker.compose.project={PROJECT}",
        "--format",
        '{{.Label "com.docker.compose.service"}} {{.Names}}',
    )
    return dict(line.split(" ", 1) for line in out.splitlines() if line.strip())


def online_benches(base: str, token: str) -> set[str]:
    return {
        b["name"] for b in http("GET", f"{base}/benches", token).body["benches"] if b.get("online")
    }


def fleet_round(engine: Engine, ports: Ports, env: dict[str, str], round_: int) -> None:
    engine.compose("down", "-v", "-t", "10", env=env)
    t0 = time.monotonic()
    engine.compose("--profile", "fleet", "up", "-d", "--no-build", env=env)
    nodes = {
        "bench-1": f"http://127.0.0.1:{ports.bench_1}",
        "bench-2": f"http://127.0.0.1:{ports.bench_2}",
    }
    for name, base in nodes.items():
        wait_health(base, f"fleet node {name}")
    containers = project_containers(engine)
    require(
        set(containers) == {"db", "nats", "bench-1", "bench-2"},
        f"the fleet profile started {sorted(containers)}",
    )
    token = engine.docker("exec", containers["bench-1"], "cat", "/fleet/admin.token").strip()
    require(
        engine.docker("exec", containers["bench-2"], "cat", "/fleet/admin.token").strip() == token,
        "both nodes see one token file",
    )
    for name, base in nodes.items():
        eventually(
            f"node {name} lists both benches online",
            partial(online_benches, base, token),
            partial(operator.eq, {"stage-1", "stage-2"}),
            90,
        )
    for name, base in nodes.items():  # each bench's tilt through either node
        for bench, owner in (("stage-1", "bench-1"), ("stage-2", "bench-2")):
            tilt = eventually(
                f"/tilt of {bench} through {name}",
                partial(http, "GET", f"{base}/tilt?bench={bench}", token),
                lambda a: a.status == 200,
                60,
            )
            require(
                tilt.body.get("node", owner) == owner,
                f"/tilt of {bench} through {name}: {tilt.body}",
            )
    tokens = http("GET", f"{nodes['bench-2']}/tokens", token)
    require(
        tokens.status == 200 and [t["name"] for t in tokens.body["tokens"]] == ["admin"],
        f"tokens: {tokens.body}",
    )
    logs = {name: engine.logs(containers[name]) for name in nodes}
    made = [
        name
        for name, log in logs.items()
        if "first start: admin token written to /fleet/admin.token" in log
    ]
    require(len(made) == 1, f"one node made the admin token: {made}")
    for name, log in logs.items():
        require(
            "Traceback" not in log and "start-up failed" not in log,
            f"node {name} log: {log[-1500:]}",
        )
        require(token not in log, f"the admin token is in node {name}'s docker logs")
        require("/fleet/admin.token" in log, f"node {name} names the token file: {log[-800:]}")
    for service, container in containers.items():
        state = engine.inspect(container)
        require(
            state["State"]["Running"] and state["RestartCount"] == 0,
            f"{service}: running {state['State']['Running']}, restarts {state['RestartCount']}",
        )
    say(
        f"compose fleet, round {round_ + 1}: db, nats, bench-1, bench-2 up in "
        f"{time.monotonic() - t0:.0f} s, none restarted; both benches online and their /tilt "
        f"through either node; one admin token, made by {made[0]}, in /fleet/admin.token as both "
        "nodes say"
    )


def published_ports(engine: Engine) -> None:
    """The host ports compose.yaml publishes, by default and as chosen (the file as it is, rendered
    by Compose)."""

    def rendered(env: dict[str, str]) -> list[str]:
        out = engine.compose_file(
            "compose.published.yaml", "--profile", "single", "--profile", "fleet", "config", env=env
        )
        return sorted(re.findall(r"(?m)^ *- (\S+:\d+:8000)(?:/tcp)?$", out))

    default = rendered({})
    require(
        default == ["127.0.0.1:8000:8000", "127.0.0.1:8001:8000", "127.0.0.1:8002:8000"],
        f"default ports: {default}",
    )
    chosen = rendered(
        {
            "TILTLAB_PUBLISH_PORT": "18000",
            "TILTLAB_PUBLISH_PORT_BENCH_1": "18001",
            "TILTLAB_PUBLISH_PORT_BENCH_2": "18002",
            "TILTLAB_PUBLISH": "0.0.0.0",
        }
    )
    require(
        chosen == ["0.0.0.0:18000:8000", "0.0.0.0:18001:8000", "0.0.0.0:18002:8000"],
        f"chosen ports: {chosen}",
    )
    say(f"compose.yaml publishes {', '.join(default)}; chosen: {', '.join(chosen)}")


def compose_runs(engine: Engine) -> None:
    ports, _ = prepare_compose(engine.work)
    env = {"TILTLAB_IMAGE": "tiltlab:ci"}
    published_ports(engine)
    for round_ in range(FLEET_ROUNDS):
        fleet_round(engine, ports, env, round_)
    engine.compose("down", "-v", "-t", "10", env=env)
    engine.compose("--profile", "single", "up", "-d", "--no-build", env=env)
    health = wait_health(f"http://127.0.0.1:{ports.single}", "the single profile's daemon")
    containers = project_containers(engine)
    require(
        set(containers) == {"db", "tiltlab"}, f"the single profile started {sorted(containers)}"
    )
    require(
        health["database"].startswith("postgresql+psycopg://tiltlab:***@127.0.0.1"),
        f"single: {health}",
    )
    say(
        f"compose single: db and tiltlab only, on PostgreSQL ({health['database']}), bench "
        f"{health['benches']}"
    )
    engine.compose("down", "-v", "-t", "10", env=env)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--docker", required=True)
    parser.add_argument("--compose", required=True)
    parser.add_argument("--image", required=True)
    parser.add_argument("--work", required=True, type=Path)
    parser.add_argument("--only", choices=("image", "compose"), default=None)
    args = parser.parse_args()
    engine = Engine(args.docker, args.compose, args.work)
    # The image alone and compose.yaml use containers and ports of their own: run side by side,
    # since most of each is waiting (a health check's interval, a database starting, a job
    # measuring).
    parts = {
        "image": partial(image_alone, engine, args.image),
        "compose": partial(compose_runs, engine),
    }
    failures: dict[str, BaseException] = {}

    def run(name: str) -> None:
        t0 = time.monotonic()
        try:
            parts[name]()
        except BaseException as exc:  # noqa: BLE001 - reported below, whatever it is
            failures[name] = exc
        say(
            f"{name} checks {'failed' if name in failures else 'passed'} in "
            f"{time.monotonic() - t0:.0f} s"
        )

    chosen = [args.only] if args.only else list(parts)
    threads = [threading.Thread(target=run, args=(name,), name=name) for name in chosen]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for name, exc in failures.items():
        say(f"FAILED ({name}): {exc if isinstance(exc, CheckFailed) else repr(exc)}")
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
