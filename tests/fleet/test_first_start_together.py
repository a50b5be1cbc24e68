"""Daemons started at the same moment on a new PostgreSQL database, as an orchestrator starts a
fleet.

They queue for the schema migration and leave it together, so they make the lab's first admin token
and register their benches and instruments at the same moment: one makes each, the others take what
it made. Every round is a new database; no daemon may crash, the database holds one admin token, it
is in one file, and every daemon names that file.
"""

from __future__ import annotations

import contextlib
import operator
import stat
from collections.abc import Iterator
from functools import partial
from pathlib import Path

import httpx
import pytest
import sqlalchemy as sa

from tests.helpers.fleet import UNREACHABLE, Daemon, NatsServer, postgres_schema_url
from tests.helpers.running_service import free_port
from tests.helpers.waiting import eventually

pytestmark = [pytest.mark.postgres, pytest.mark.slow]

ROUNDS = 2  # each a new database: the race is met again every time


@contextlib.contextmanager
def started_together(daemons: list[Daemon]) -> Iterator[list[Daemon]]:
    """Every process launched before any is waited for; all stopped afterwards, however the test
    ends."""
    with contextlib.ExitStack() as stack:
        for daemon in daemons:
            daemon.launch()
            stack.push(daemon.__exit__)
        for daemon in daemons:
            daemon.wait_serving(timeout_s=150)
        yield daemons


def _rows(url: str, query: str) -> list[tuple[object, ...]]:
    engine = sa.create_engine(url)
    try:
        with engine.connect() as conn:
            return [tuple(row) for row in conn.execute(sa.text(query))]
    finally:
        engine.dispose()


def _online_benches(daemon: Daemon, auth: dict[str, str]) -> set[str]:
    listing = httpx.get(f"{daemon.url}/benches", headers=auth, timeout=10).json()["benches"]
    return {b["name"] for b in listing if b.get("online")}


def _assert_one_token_in_one_file(url: str, daemons: list[Daemon], token_file: Path) -> str:
    """One admin token in the database, in `token_file` (0600), made by one daemon and named by
    every one."""
    assert _rows(url, "SELECT name, scopes FROM api_tokens") == [("admin", ["admin"])]
    assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
    token = token_file.read_text().strip()
    logs = [d.log.read_text() for d in daemons]
    made = [
        log
        for log in logs
        if f"tiltlab: first start: admin token written to {token_file} (mode 0600)" in log
    ]
    assert len(made) == 1, logs
    for log in logs:
        assert "Traceback" not in log and "ConflictError" not in log, log
        assert token not in log, "the token went to a log that is not a terminal"
        assert str(token_file) in log.split("tiltlab: dashboard:", 1)[1].splitlines()[0], log
    return token


@pytest.mark.parametrize("count", [2, 3])
def test_fleet_daemons_started_together_make_one_admin_token_in_the_named_file(
    tmp_path: Path, count: int
) -> None:
    for round_ in range(ROUNDS):
        here = tmp_path / f"round-{round_}"
        broker = NatsServer(here / "nats", free_port())
        broker.start()
        try:
            with postgres_schema_url() as url:
                token_file = here / "shared" / "admin.token"  # a folder every node mounts
                common = {
                    "TILTLAB_DATABASE_URL": url,
                    "TILTLAB_BROKER_URL": broker.url,
                    "TILTLAB_SIM_SPEED": "20",
                    "TILTLAB_ADMIN_TOKEN_FILE": str(token_file),
                    "TILTLAB_DATABASE_WAIT_S": "60",
                }
                daemons = [
                    Daemon(
                        here / f"node-{i}",
                        {
                            **common,
                            "TILTLAB_NODE": f"node-{i}",
                            "TILTLAB_SIM_BENCH_NAME": f"stage-{i}",
                        },
                    )
                    for i in range(count)
                ]
                with started_together(daemons):
                    token = _assert_one_token_in_one_file(url, daemons, token_file)
                    auth = {"Authorization": f"Bearer {token}"}
                    names = {f"stage-{i}" for i in range(count)}
                    # the token works on every node, and each lists every bench online
                    for daemon in daemons:
                        eventually(
                            partial(_online_benches, daemon, auth),
                            until=partial(operator.eq, names),
                            timeout_s=60,
                            every_s=0.2,
                            ignoring=UNREACHABLE,
                            what="every bench online",
                        )
                    assert all(d.proc is not None and d.proc.poll() is None for d in daemons)
                    assert sorted(n for (n,) in _rows(url, "SELECT name FROM benches")) == sorted(
                        names
                    )
                    # the simulated stage controller is one serial number on every simulated bench:
                    # one device row
                    assert _rows(url, "SELECT count(*) FROM devices WHERE model = 'SC-200SIM'") == [
                        (1,)
                    ]
        finally:
            broker.stop()


def test_without_a_named_file_every_daemon_names_the_one_the_first_wrote(tmp_path: Path) -> None:
    for round_ in range(1):
        here = tmp_path / f"round-{round_}"
        broker = NatsServer(here / "nats", free_port())
        broker.start()
        try:
            with postgres_schema_url() as url:
                common = {
                    "TILTLAB_DATABASE_URL": url,
                    "TILTLAB_BROKER_URL": broker.url,
                    "TILTLAB_SIM_SPEED": "20",
                    "TILTLAB_DATABASE_WAIT_S": "60",
                }
                daemons = [
                    Daemon(
                        here / f"node-{i}",
                        {
                            **common,
                            "TILTLAB_NODE": f"node-{i}",
                            "TILTLAB_SIM_BENCH_NAME": f"stage-{i}",
                        },
                    )
                    for i in range(3)
                ]
                with started_together(daemons):
                    written = [d for d in daemons if (d.data_dir / "admin.token").exists()]
                    assert len(written) == 1
                    maker = written[0]
                    token_file = maker.data_dir / "admin.token"
                    _assert_one_token_in_one_file(url, daemons, token_file)
                    for daemon in daemons:
                        if daemon is not maker:
                            node = maker.env["TILTLAB_NODE"]
                            assert (
                                f"which node {node} wrote to {token_file} at its first start"
                                in daemon.log.read_text()
                            )
        finally:
            broker.stop()


def test_daemons_of_one_bench_name_without_a_broker_register_it_once(tmp_path: Path) -> None:
    for round_ in range(1):
        here = tmp_path / f"round-{round_}"
        with postgres_schema_url() as url:
            token_file = here / "shared" / "admin.token"
            common = {
                "TILTLAB_DATABASE_URL": url,
                "TILTLAB_SIM_SPEED": "20",
                "TILTLAB_ADMIN_TOKEN_FILE": str(token_file),
                "TILTLAB_DATABASE_WAIT_S": "60",
            }
            daemons = [
                Daemon(here / f"alone-{i}", {**common, "TILTLAB_NODE": f"alone-{i}"})
                for i in range(2)
            ]
            with started_together(daemons):
                _assert_one_token_in_one_file(url, daemons, token_file)
                assert _rows(url, "SELECT name FROM benches") == [("sim-stage",)]
                assert all(d.proc is not None and d.proc.poll() is None for d in daemons)


def test_a_node_started_or_stopped_beside_a_running_job_leaves_it_running(tmp_path: Path) -> None:
    """Nodes start and stop in any order: a node that starts (or stops) marks only its own benches'
    unfinished jobs interrupted, never a job another node is running. The job is long (100 points),
    so it is still measuring while the other node comes and goes; it measures on afterwards, and is
    then cancelled."""
    broker = NatsServer(tmp_path / "nats", free_port())
    broker.start()
    try:
        with postgres_schema_url() as url:
            common = {
                "TILTLAB_DATABASE_URL": url,
                "TILTLAB_BROKER_URL": broker.url,
                "TILTLAB_SIM_SPEED": "20",
                "TILTLAB_ADMIN_TOKEN_FILE": str(tmp_path / "shared" / "admin.token"),
            }
            with Daemon(
                tmp_path / "a",
                {**common, "TILTLAB_NODE": "node-a", "TILTLAB_SIM_BENCH_NAME": "stage-a"},
            ) as a:
                secret = (tmp_path / "shared" / "admin.token").read_text().strip()
                auth = {"Authorization": f"Bearer {secret}"}
                started = httpx.post(
                    f"{a.url}/calibrations",
                    headers=auth,
                    timeout=30,
                    json={
                        "procedure": "stage-grid",
                        "method": "kinematic",
                        "grid": {"x_deg": [-4, 4], "y_deg": [-4, 4], "n_x": 10, "n_y": 10},
                    },
                )
                assert started.status_code == 202, started.text
                job_url = f"{a.url}/calibrations/{started.json()['id']}"

                def job() -> dict:
                    return dict(httpx.get(job_url, headers=auth, timeout=10).json())

                eventually(
                    job,
                    until=lambda j: j["state"] == "running" and j["progress"]["points_done"] >= 1,
                    timeout_s=120,
                    every_s=0.2,
                    ignoring=UNREACHABLE,
                    what="the job running with a point done",
                )
                with Daemon(
                    tmp_path / "b",
                    {**common, "TILTLAB_NODE": "node-b", "TILTLAB_SIM_BENCH_NAME": "stage-b"},
                ):
                    assert job()["state"] == "running"
                after = job()  # node b has stopped
                assert after["state"] == "running" and not after["interrupted"], after
                eventually(
                    job,
                    until=lambda j: j["progress"]["points_done"] > after["progress"]["points_done"],
                    timeout_s=120,
                    every_s=0.2,
                    ignoring=UNREACHABLE,
                    what="the job going on past where it was",
                )
                cancelled = httpx.post(f"{job_url}/cancel", headers=auth, timeout=30)
                assert cancelled.status_code in (200, 202), cancelled.text
                ended = eventually(
                    job,
                    until=lambda j: j["state"] != "running",
                    timeout_s=120,
                    every_s=0.2,
                    ignoring=UNREACHABLE,
                    what="the job no longer running",
                )
                assert ended["state"] == "cancelled" and not ended["interrupted"], ended
    finally:
        broker.stop()
