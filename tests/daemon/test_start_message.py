"""Every start says where the dashboard is and where its token comes from, never printing the token
again."""

from __future__ import annotations

import os
import pty
import re
import select
import socket
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from service.errors import InputError
from tests.helpers.daemon import make_client
from tests.helpers.processes import spawn
from tests.helpers.running_service import free_port
from tests.helpers.waiting import eventually


def test_later_starts_name_the_dashboard_and_the_token_file(tmp_path, capsys):
    with make_client(tmp_path):
        pass
    token = (tmp_path / "admin.token").read_text().strip()
    capsys.readouterr()
    with make_client(tmp_path):
        err = capsys.readouterr().err
    assert (
        "tiltlab: dashboard: http://127.0.0.1:8000/" in err and str(tmp_path / "admin.token") in err
    )
    assert token not in err
    (tmp_path / "admin.token").unlink()
    with make_client(tmp_path):
        assert "tiltlab token create" in capsys.readouterr().err


def test_without_authentication_the_dashboard_is_named(tmp_path, capsys):
    with make_client(tmp_path, auth="none"):
        err = capsys.readouterr().err
    assert "tiltlab: dashboard: http://127.0.0.1:8000/ (authentication off)" in err
    assert not (tmp_path / "admin.token").exists()


def _first_start(tmp_path: Path, *, terminal: bool) -> str:
    """`tiltlab serve` started on a new data directory, its standard error a pseudo-terminal (as in
    a shell) or a file (as under a service manager or in a container): what it says up to its
    dashboard line."""
    data = tmp_path / "data"
    env = {**os.environ, "TILTLAB_DATA_DIR": str(data), "TILTLAB_SIM_SPEED": "20"}
    env.pop("TILTLAB_CONFIG", None)
    command = [sys.executable, "-m", "service", "serve", "--port", str(free_port())]
    if terminal:
        parent, child = pty.openpty()
        proc = spawn(command, env=env, stdin=subprocess.DEVNULL, stdout=child, stderr=child)
        os.close(child)
        out = bytearray()

        def said_its_dashboard_line() -> bool:
            if b"tiltlab: dashboard:" not in out or not out.rstrip(b" ").endswith(b"\n"):
                assert proc.poll() is None, out.decode(errors="replace")
                if select.select([parent], [], [], 0.5)[0]:
                    out.extend(os.read(parent, 4096))
            return b"tiltlab: dashboard:" in out and out.rstrip(b" ").endswith(b"\n")

        try:
            eventually(
                said_its_dashboard_line,
                timeout_s=90,
                every_s=0,
                what=lambda: f"the dashboard line in: {out.decode(errors='replace')}",
            )
        finally:
            proc.terminate()
            proc.wait(timeout=30)
            os.close(parent)
        return out.decode().replace("\r\n", "\n")
    tmp_path.mkdir(parents=True, exist_ok=True)
    log = tmp_path / "serve.log"
    with log.open("wb") as sink:
        proc = spawn(command, env=env, stdin=subprocess.DEVNULL, stdout=sink, stderr=sink)

        def logged_its_dashboard_line() -> bool:
            if "tiltlab: dashboard:" in log.read_text():
                return True
            assert proc.poll() is None, log.read_text()
            return False

        try:
            eventually(
                logged_its_dashboard_line,
                timeout_s=90,
                every_s=0.2,
                what=lambda: f"the dashboard line in: {log.read_text()}",
            )
        finally:
            proc.terminate()
            proc.wait(timeout=30)
    return log.read_text()


def test_the_first_admin_token_is_shown_only_on_an_interactive_terminal(tmp_path):
    shown = _first_start(tmp_path / "terminal", terminal=True)
    path = tmp_path / "terminal" / "data" / "admin.token"
    token = path.read_text().strip()
    assert f"tiltlab: dashboard: http://127.0.0.1:{_port(shown)}/#token={token}" in shown

    logged = _first_start(tmp_path / "log", terminal=False)
    path = tmp_path / "log" / "data" / "admin.token"
    token = path.read_text().strip()
    assert token not in logged and "#token=" not in logged
    assert f"tiltlab: first start: admin token written to {path} (mode 0600)" in logged
    assert (
        f"tiltlab: dashboard: http://127.0.0.1:{_port(logged)}/ (token: the admin token in {path})"
        in logged
    )


def _port(text: str) -> str:
    match = re.search(r"dashboard: http://127\.0\.0\.1:(\d+)/", text)
    assert match, text
    return match.group(1)


def test_the_admin_token_file_can_be_named(tmp_path, capsys):
    shared = tmp_path / "shared" / "lab-admin.token"
    with make_client(tmp_path / "a", admin_token_file=shared):
        err = capsys.readouterr().err
    assert (
        stat.S_IMODE(shared.stat().st_mode) == 0o600
        and not (tmp_path / "a" / "admin.token").exists()
    )
    assert f"admin token written to {shared} (mode 0600)" in err
    with make_client(tmp_path / "a", admin_token_file=shared):
        assert f"(token: the admin token in {shared})" in capsys.readouterr().err
    # the file named no longer: where the first start wrote it is recorded
    with make_client(tmp_path / "a"):
        err = capsys.readouterr().err
    assert (
        f"the lab's first admin token, which node {socket.gethostname()} wrote to {shared} at its "
        "first start" in err
    )


def test_an_admin_token_file_that_cannot_be_written_stops_the_first_start(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    with pytest.raises(
        InputError,
        match="TILTLAB_ADMIN_TOKEN_FILE: the first admin token cannot be written to "
        f"{blocker}/admin.token",
    ):
        with make_client(tmp_path / "data", admin_token_file=blocker / "admin.token"):
            pass
    # nothing was kept: the next start makes the token
    with make_client(tmp_path / "data") as client:
        token = (tmp_path / "data" / "admin.token").read_text().strip()
        assert (
            client.get("/benches", headers={"Authorization": f"Bearer {token}"}).status_code == 200
        )
