"""The diagnosis worker processes end with the daemon, however it ends (SIGTERM, Ctrl-C, SIGKILL, a
failure at start-up), and the diagnoses queued or running at once are bounded (503 with Retry-After
beyond).

The test process makes itself the "subreaper" of what it starts (Linux): a process the daemon leaves
behind is then handed to the test, not to init, and is seen.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.helpers.daemon import admin_headers, make_client, wait_job
from tests.helpers.diagnosis import SMALL_BODY
from tests.helpers.processes import spawn
from tests.helpers.running_service import free_port
from tests.helpers.waiting import eventually

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="follows processes through /proc (Linux)"
)
PR_SET_CHILD_SUBREAPER = 36


@contextlib.contextmanager
def subreaper() -> Iterator[set[int]]:
    """This test process adopts whatever its daemon leaves behind; yields the children it had
    already (the suite's own, such as a multiprocessing resource tracker of an earlier test), which
    are not the daemon's."""
    libc = ctypes.CDLL(None, use_errno=True)
    before = set(_children())
    assert libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) == 0
    try:
        yield before
    finally:
        libc.prctl(PR_SET_CHILD_SUBREAPER, 0, 0, 0, 0)
        for pid in set(_children()) - before:  # whatever was left behind (the test has failed then)
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        _reap()


def _children() -> list[int]:
    """Live processes whose parent is this test process (zombies reaped and left out)."""
    _reap()
    me, out = os.getpid(), []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError):
            text = stat.read_text()
            fields = text[text.rindex(")") + 2 :].split()
            if int(fields[1]) == me and fields[0] != "Z":
                out.append(int(stat.parent.name))
    return out


def _reap() -> None:
    with contextlib.suppress(ChildProcessError):
        while os.waitpid(-1, os.WNOHANG)[0]:
            pass


def _cmdline(pid: int) -> str:
    """The process's command line; empty once it has gone."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
    except OSError:
        return ""


def _descendants(pid: int) -> list[int]:
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError):
            text = stat.read_text()
            if int(text[text.rindex(")") + 2 :].split()[1]) == pid:
                kids.append(int(stat.parent.name))
    return kids + [d for k in kids for d in _descendants(k)]


@pytest.fixture(scope="module")
def with_a_record(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    """A data directory holding a stage record to diagnose (made once by an in-process daemon)."""
    data = tmp_path_factory.mktemp("record")
    with make_client(data) as client:
        h = admin_headers(data)
        r = client.post("/calibrations", headers=h, json=SMALL_BODY)
        assert r.status_code == 202, r.text
        job = wait_job(client, r.json()["id"], h)
        assert job["state"] == "succeeded", job
        return data, job["record"]["id"]


def _serve(data: Path, **env: str) -> tuple[subprocess.Popen[bytes], str, dict[str, str]]:
    port = free_port()
    proc = spawn(
        [sys.executable, "-m", "service", "serve", "--port", str(port)],
        env={
            **os.environ,
            "TILTLAB_DATA_DIR": str(data),
            "TILTLAB_SIM_SPEED": "20",
            "TILTLAB_SIM_TRANSPORT": "loopback",
            **env,
        },
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    base = f"http://127.0.0.1:{port}"

    def serving() -> bool:
        assert proc.poll() is None, "the daemon did not start: it exited"
        return httpx.get(f"{base}/health", timeout=2).status_code == 200

    eventually(
        serving,
        timeout_s=90,
        every_s=0.2,
        ignoring=(httpx.TransportError,),
        what="the daemon answering /health",
    )
    return proc, base, admin_headers(data)


@pytest.mark.parametrize(
    "how", [signal.SIGTERM, signal.SIGINT, signal.SIGKILL], ids=["SIGTERM", "SIGINT", "SIGKILL"]
)
def test_no_worker_process_is_left_after_the_daemon_exits(
    with_a_record: tuple[Path, int], tmp_path: Path, how: signal.Signals
) -> None:
    source, record_id = with_a_record
    data = tmp_path / "data"
    shutil.copytree(source, data)
    with subreaper() as before:
        proc, base, h = _serve(data)
        try:
            for _ in range(2):  # one running in the worker, one waiting for it
                r = httpx.post(
                    f"{base}/records/{record_id}/diagnose", headers=h, json={}, timeout=60
                )
                assert r.status_code == 202, r.text
            eventually(
                lambda: any("multiprocessing" in _cmdline(p) for p in _descendants(proc.pid)),
                timeout_s=60,
                every_s=0.1,
                what="a worker process started",
            )
            started = _descendants(proc.pid)
            proc.send_signal(how)
            proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        eventually(
            lambda: {p: _cmdline(p)[:120] for p in set(_children()) - before},
            until=lambda left: not left,
            timeout_s=30,
            every_s=0.2,
            what=f"none of the daemon's {len(started)} processes outliving it after {how.name}",
        )


@pytest.mark.postgres
def test_no_process_is_left_after_a_failure_at_start_up(tmp_path: Path) -> None:
    """A daemon whose start fails once its bench runs (the bench's name is owned by another live
    node of the fleet: exit 2) leaves nothing running."""
    from tests.helpers.fleet import Daemon as FleetDaemon
    from tests.helpers.fleet import NatsServer, postgres_schema_url

    server = NatsServer(tmp_path / "nats", free_port())
    server.start()
    try:
        with postgres_schema_url() as url:
            common = {
                "TILTLAB_DATABASE_URL": url,
                "TILTLAB_BROKER_URL": server.url,
                "TILTLAB_SIM_BENCH_NAME": "bench-a",
                "TILTLAB_SIM_TRANSPORT": "loopback",
            }
            with FleetDaemon(tmp_path / "a", {**common, "TILTLAB_NODE": "node-a"}), subreaper():
                ours = set(_children())  # the broker and the first node: the test's own
                r = subprocess.run(
                    [sys.executable, "-m", "service", "serve", "--port", str(free_port())],
                    env={
                        **os.environ,
                        **common,
                        "TILTLAB_DATA_DIR": str(tmp_path / "b"),
                        "TILTLAB_NODE": "node-b",
                    },
                    capture_output=True,
                    text=True,
                    timeout=180,
                )
                assert r.returncode == 2 and "bench-a" in r.stderr, r.stderr[-2000:]
                eventually(
                    lambda: set(_children()) - ours,
                    until=lambda left: not left,
                    timeout_s=30,
                    every_s=0.2,
                    what="no process outliving the failed start",
                )
    finally:
        server.stop()


def test_diagnoses_beyond_the_bound_are_503_with_retry_after(
    with_a_record: tuple[Path, int], tmp_path: Path
) -> None:
    source, record_id = with_a_record
    data = tmp_path / "data"
    shutil.copytree(source, data)
    with subreaper():
        proc, base, h = _serve(data, TILTLAB_MAX_DIAGNOSES="2")
        try:
            answers = [
                httpx.post(f"{base}/records/{record_id}/diagnose", headers=h, json={}, timeout=60)
                for _ in range(5)
            ]
            assert [a.status_code for a in answers[:2]] == [202, 202], [a.text for a in answers]
            refused = [a for a in answers[2:] if a.status_code != 202]
            assert refused and all(a.status_code == 503 for a in refused), [a.text for a in answers]
            assert (
                int(refused[0].headers["retry-after"]) > 0
                and "TILTLAB_MAX_DIAGNOSES" in refused[0].json()["detail"]
            )
            listed = httpx.get(f"{base}/diagnoses", headers=h, timeout=60).json()["diagnoses"]
            assert len(listed) == 5 - len(refused)  # a refused diagnosis leaves nothing behind
        finally:
            proc.terminate()
            proc.wait(timeout=60)
