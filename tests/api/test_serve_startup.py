"""`tiltlab serve` start-up: it binds before it announces, and every start-up failure is one line
naming the setting and what to do (exit 2 for a setting that cannot work, 1 for surroundings)."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import httpx
import pytest

from tests.helpers.processes import spawn
from tests.helpers.running_service import free_port


def _serve(tmp_path: Path, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    full_env = {**os.environ, "TILTLAB_DATA_DIR": str(tmp_path / "data"), **env}
    full_env.pop("TILTLAB_CONFIG", None)
    return subprocess.run(
        [sys.executable, "-m", "service", "serve", *args],
        env=full_env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def _one_line(r: subprocess.CompletedProcess[str], *words: str) -> str:
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert "Traceback" not in r.stderr, r.stderr
    assert "serving on" not in r.stderr
    last = lines[-1]
    for w in words:
        assert w in last, last
    return last


def test_port_out_of_range(tmp_path: Path) -> None:
    r = _serve(tmp_path, "--port", "70000")
    assert r.returncode == 2
    _one_line(r, "--port", "70000", "1 to 65535")
    r = _serve(tmp_path, TILTLAB_PORT="70000")
    assert r.returncode == 2
    _one_line(r, "TILTLAB_PORT", "70000")


def test_port_in_use(tmp_path: Path) -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        r = _serve(tmp_path, "--port", str(port))
    assert r.returncode == 1
    _one_line(r, f"--port {port}", "already in use", "another port")


def test_unknown_host(tmp_path: Path) -> None:
    r = _serve(tmp_path, "--host", "no-such-host.invalid", "--port", str(free_port()))
    assert r.returncode == 2
    _one_line(r, "--host no-such-host.invalid", "TILTLAB_HOST")


def test_unwritable_data_directory(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    r = _serve(tmp_path, "--port", str(free_port()), TILTLAB_DATA_DIR=str(blocker / "data"))
    assert r.returncode == 2
    _one_line(r, "TILTLAB_DATA_DIR", "writable")
    assert blocker.read_text() == "not a folder"


def test_sqlite_file_in_an_impossible_folder(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    r = _serve(
        tmp_path,
        "--port",
        str(free_port()),
        TILTLAB_DATABASE_URL=f"sqlite:///{blocker}/db/tiltlab.db",
    )
    assert r.returncode == 2
    _one_line(r, "TILTLAB_DATABASE_URL", str(blocker / "db"), "a folder this user can write")
    assert blocker.read_text() == "not a folder"


def test_unreachable_database_is_retried_then_one_line(tmp_path: Path) -> None:
    dead = free_port()  # nothing listens there
    r = _serve(
        tmp_path,
        "--port",
        str(free_port()),
        "--database-wait-s",
        "1",
        TILTLAB_DATABASE_URL=f"postgresql+psycopg://lab@127.0.0.1:{dead}/tiltlab",
    )
    assert r.returncode == 1
    assert "retrying for up to 1 s" in r.stderr
    _one_line(r, "TILTLAB_DATABASE_URL", "no answer after 1 s", "TILTLAB_DATABASE_WAIT_S")


def test_wait_setting_is_validated(tmp_path: Path) -> None:
    r = _serve(tmp_path, "--database-wait-s", "nan")
    assert r.returncode == 2
    _one_line(r, "--database-wait-s")
    r = _serve(tmp_path, TILTLAB_DATABASE_WAIT_S="-1")
    assert r.returncode == 2
    _one_line(r, "TILTLAB_DATABASE_WAIT_S")


def test_announces_only_once_listening(tmp_path: Path) -> None:
    port = free_port()
    env = {**os.environ, "TILTLAB_DATA_DIR": str(tmp_path / "data")}
    env.pop("TILTLAB_CONFIG", None)
    proc = spawn(
        [sys.executable, "-m", "service", "serve", "--port", str(port)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    killer = threading.Timer(90, proc.kill)  # a hung start-up fails the test instead of hanging it
    killer.start()
    try:
        seen = []
        for line in proc.stderr:
            seen.append(line)
            if "serving on" in line:
                assert f"http://127.0.0.1:{port}" in line
                # the moment it says so, a client must get through: no retry here
                with socket.create_connection(("127.0.0.1", port), timeout=5) as conn:
                    conn.sendall(b"GET /health HTTP/1.0\r\n\r\n")
                    assert conn.recv(12).startswith(b"HTTP/1.")
                break
        else:
            pytest.fail("the service never announced itself: " + "".join(seen))
        proc.send_signal(signal.SIGINT)
        rest = proc.stderr.read()
        assert proc.wait(timeout=30) == 0
        assert "Traceback" not in rest
    finally:
        killer.cancel()
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_names_each_device_that_does_not_answer(tmp_path: Path) -> None:
    """A bench whose ports lead nowhere starts, and says on the console which role on which port is
    silent."""
    config = tmp_path / "bench.toml"
    config.write_text(
        '[benches.lab-1]\nkind = "stage"\n'
        f'[benches.lab-1.roles.reference_sensor]\nport = "{tmp_path}/no-reference"\n'
        f'[benches.lab-1.roles.measurement_sensor]\nport = "{tmp_path}/no-measurement"\n'
        f'[benches.lab-1.roles.stage]\nport = "{tmp_path}/no-stage"\n'
    )
    port = free_port()
    env = {**os.environ, "TILTLAB_DATA_DIR": str(tmp_path / "data")}
    env.pop("TILTLAB_CONFIG", None)
    proc = spawn(
        [
            sys.executable,
            "-m",
            "service",
            "serve",
            "--port",
            str(port),
            "--bench-config",
            str(config),
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    killer = threading.Timer(120, proc.kill)
    killer.start()
    try:
        seen: list[str] = []
        for line in proc.stderr:  # type: ignore[union-attr]
            seen.append(line)
            if "serving on" in line:
                break
        after = [proc.stderr.readline() for _ in range(3)]  # type: ignore[union-attr]
        text = "".join(after)
        for role, path in (
            ("reference_sensor", "no-reference"),
            ("measurement_sensor", "no-measurement"),
            ("stage", "no-stage"),
        ):
            line = next((x for x in after if f" {role} on " in x), None)
            assert line is not None, (role, seen, text)
            assert (
                "bench lab-1" in line and f"{tmp_path}/{path}" in line and "does not answer" in line
            ), line
    finally:
        killer.cancel()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.mark.skipif(
    shutil.which("openssl") is None, reason="makes its test certificate with openssl"
)
def test_serves_https_with_a_certificate(tmp_path: Path) -> None:
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(
        [
            "openssl",
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-days",
            "2",
            "-subj",
            "/CN=127.0.0.1",
            "-addext",
            "subjectAltName=IP:127.0.0.1",
            "-keyout",
            str(key),
            "-out",
            str(cert),
        ],
        check=True,
        capture_output=True,
        timeout=60,
    )
    port = free_port()
    env = {**os.environ, "TILTLAB_DATA_DIR": str(tmp_path / "data")}
    env.pop("TILTLAB_CONFIG", None)
    proc = spawn(
        [
            sys.executable,
            "-m",
            "service",
            "serve",
            "--port",
            str(port),
            "--ssl-certfile",
            str(cert),
            "--ssl-keyfile",
            str(key),
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    killer = threading.Timer(120, proc.kill)
    killer.start()
    try:
        for line in proc.stderr:  # type: ignore[union-attr]
            if "serving on" in line:
                assert f"https://127.0.0.1:{port}" in line, line
                break
        r = httpx.get(f"https://127.0.0.1:{port}/health", verify=str(cert), timeout=30)
        assert r.status_code == 200 and r.json()["version"]
    finally:
        killer.cancel()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_half_a_certificate_is_refused(tmp_path: Path) -> None:
    r = _serve(tmp_path, "--port", str(free_port()), "--ssl-certfile", str(tmp_path / "cert.pem"))
    assert r.returncode == 2
    _one_line(r, "--ssl-certfile", "--ssl-keyfile")


@pytest.mark.parametrize(
    ("typo", "meant"),
    [("sim_sped = 5.0", "sim_speed"), ('databse_url = "sqlite:////tmp/x.db"', "database_url")],
)
def test_unknown_key_in_the_settings_file_is_refused(tmp_path: Path, typo: str, meant: str) -> None:
    """A typo in TILTLAB_CONFIG is not silently ignored (the daemon would start on defaults): exit 2
    naming it."""
    cfg = tmp_path / "tiltlab.toml"
    cfg.write_text(f"port = {free_port()}\n{typo}\n")
    env = {**os.environ, "TILTLAB_DATA_DIR": str(tmp_path / "data"), "TILTLAB_CONFIG": str(cfg)}
    r = subprocess.run(
        [sys.executable, "-m", "service", "serve"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2, r.stderr
    key = typo.split(" ")[0]
    _one_line(r, "TILTLAB_CONFIG", str(cfg), f"{key}: no such setting", f"did you mean {meant}?")
    assert not (tmp_path / "data" / "tiltlab.db").exists()  # refused before anything was made
