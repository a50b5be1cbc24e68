"""A sick database never stops the daemon: `/health` and `/tilt` keep their latency while PostgreSQL
hangs (a proxy in front of it that accepts and never answers) and while another client holds
`api_tokens` locked, even as strangers send tokens the daemon has never seen. Those are answered 503
naming the database once the request deadline passes (TILTLAB_DB_REQUEST_TIMEOUT_S), never by
freezing everything else.

Latencies are compared with the same run's idle baseline (percentile over percentile), never with an
absolute time: the machine is shared.
"""

from __future__ import annotations

import contextlib
import secrets
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import sqlalchemy as sa

from tests.helpers.fleet import Daemon
from tests.helpers.pg_proxy import PgProxy
from tests.helpers.waiting import eventually

pytestmark = [pytest.mark.postgres]

REQUEST_TIMEOUT_S = 2  # TILTLAB_DB_REQUEST_TIMEOUT_S of the daemon under test
SAMPLES = 300  # requests per route and phase
P50_RATIO = 3.0
P99_RATIO = 5.0


def _latencies(client: httpx.Client, token: str) -> dict[str, list[float]]:
    """SAMPLES requests to each of /health and /tilt (a token the daemon knows), alternated; seconds
    each."""
    out: dict[str, list[float]] = {"/health": [], "/tilt": []}
    auth = {"Authorization": f"Bearer {token}"}
    for _ in range(SAMPLES):
        for path in out:
            t0 = time.perf_counter()
            r = client.get(path, headers=auth if path == "/tilt" else None)
            out[path].append(time.perf_counter() - t0)
            assert r.status_code == 200, (path, r.status_code, r.text)
        time.sleep(0.004)
    return out


@contextlib.contextmanager
def strangers(url: str, threads: int = 4) -> Iterator[list[httpx.Response]]:
    """Clients sending tokens nobody has seen (each needs the database), a few a second each, as a
    LIMS with a wrong token or a scanner would; their answers are collected."""
    answers: list[httpx.Response] = []
    stop = threading.Event()

    def send() -> None:
        with httpx.Client(base_url=url, timeout=120) as c:
            while not stop.is_set():
                answers.append(
                    c.get(
                        "/records",
                        headers={"Authorization": f"Bearer tl_{secrets.token_urlsafe(32)}"},
                    )
                )
                stop.wait(0.2)

    workers = [threading.Thread(target=send, daemon=True) for _ in range(threads)]
    for w in workers:
        w.start()
    try:
        yield answers
    finally:
        stop.set()
        for w in workers:
            w.join(timeout=120)


def _compare(idle: dict[str, list[float]], sick: dict[str, list[float]], what: str) -> None:
    for path in idle:
        base50, base99 = np.percentile(idle[path], [50, 99])
        sick50, sick99 = np.percentile(sick[path], [50, 99])
        figures = (
            f"{what}, {path}: idle p50 {base50 * 1e3:.2f} ms p99 {base99 * 1e3:.2f} ms;"
            f" {what} p50 {sick50 * 1e3:.2f} ms p99 {sick99 * 1e3:.2f} ms"
        )
        print(figures)
        assert sick50 <= P50_RATIO * base50, figures
        assert sick99 <= P99_RATIO * base99, figures


def _known_token(daemon: Daemon) -> str:
    admin = {"Authorization": "Bearer " + (daemon.data_dir / "admin.token").read_text().strip()}
    made = httpx.post(
        f"{daemon.url}/tokens",
        json={"name": "poller", "scopes": ["read"]},
        headers=admin,
        timeout=30,
    )
    assert made.status_code == 201, made.text
    token = made.json()["token"]
    assert (
        httpx.get(
            f"{daemon.url}/tilt", headers={"Authorization": f"Bearer {token}"}, timeout=30
        ).status_code
        == 200
    )
    return token


def _daemon_env(url: str) -> dict[str, str]:
    return {
        "TILTLAB_DATABASE_URL": url,
        "TILTLAB_DB_REQUEST_TIMEOUT_S": str(REQUEST_TIMEOUT_S),
        "TILTLAB_SIM_TRANSPORT": "loopback",
    }


def _named_the_database(answers: list[httpx.Response]) -> None:
    assert answers, "no stranger's request was answered"
    assert {r.status_code for r in answers} == {503}, {r.status_code for r in answers}
    for r in answers:
        body = r.json()
        assert (
            r.headers["content-type"].startswith("application/problem+json")
            and "database" in body["detail"]
        )
        assert r.headers.get("retry-after"), r.headers


def test_health_and_tilt_keep_their_latency_while_the_database_hangs(
    tmp_path: Path, database_url: str, proxy: PgProxy
) -> None:
    with Daemon(tmp_path / "node", _daemon_env(proxy.url_of(database_url))) as daemon:
        token = _known_token(daemon)
        with httpx.Client(base_url=daemon.url, timeout=120) as client:
            idle = _latencies(client, token)
            # PostgreSQL accepts nothing more and answers nothing: no TCP timeout notices
            proxy.hang()
            with strangers(daemon.url) as answers:
                # the first strangers' checks have met their deadline
                time.sleep(REQUEST_TIMEOUT_S + 1)
                sick = _latencies(client, token)
            health = client.get("/health").json()
            ready = client.get("/ready")
        _named_the_database(answers)
        _compare(idle, sick, "database hung")
        # the daemon says what it found: the database is not answering
        assert health["database_state"] == "away" and ready.status_code == 503, (health, ready.text)
        assert any("database" in reason for reason in ready.json()["reasons"]), ready.text


def test_health_and_tilt_keep_their_latency_while_api_tokens_is_locked(
    tmp_path: Path, database_url: str
) -> None:
    with Daemon(tmp_path / "node", _daemon_env(database_url)) as daemon:
        token = _known_token(daemon)
        locker = sa.create_engine(database_url)
        try:
            with httpx.Client(base_url=daemon.url, timeout=120) as client:
                idle = _latencies(client, token)
                with locker.connect() as conn:
                    trans = conn.begin()
                    conn.execute(sa.text("LOCK TABLE api_tokens IN ACCESS EXCLUSIVE MODE"))
                    with strangers(daemon.url) as answers:
                        time.sleep(REQUEST_TIMEOUT_S + 1)
                        sick = _latencies(client, token)
                    trans.rollback()
                # the lock gone, an unseen valid token is checked again as before, once the
                # daemon's next look at the database has found it back (503 until then)
                admin = {
                    "Authorization": "Bearer "
                    + (daemon.data_dir / "admin.token").read_text().strip()
                }
                eventually(
                    lambda: client.get("/records", headers=admin).status_code,
                    until=lambda status: status == 200,
                    timeout_s=30,
                    every_s=0.2,
                    what="/records answering 200 after the lock is gone",
                )
        finally:
            locker.dispose()
        _named_the_database(answers)
        _compare(idle, sick, "api_tokens locked")
