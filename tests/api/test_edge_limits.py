"""The daemon's edge against strangers and leaks, on `tiltlab serve` as people start it: a huge body
without a token is refused before it is read, no token reaches the log, a revoked token's streams
end."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from tests.helpers.logged_daemon import Daemon, logged_daemon, tiltlab_cli
from tests.helpers.raw_http import MIB, parse_problem, response_while_sending

GIB = 1 << 30


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    with logged_daemon(tmp_path_factory.mktemp("edge")) as d:
        yield d


def test_a_declared_gigabyte_without_a_token_is_refused_before_it_is_read(daemon: Daemon) -> None:
    rss_before, peak_before = daemon.rss_kb("VmRSS"), daemon.rss_kb("VmHWM")
    head = (
        f"POST /calibrations HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        f"Content-Length: {GIB}\r\n\r\n"
    ).encode()
    answer, sent = response_while_sending(daemon.port, head, b"0" * 65536, 2 * MIB)
    status, headers, problem = parse_problem(answer)
    assert status == 413 and headers["content-type"] == "application/problem+json", answer[:300]
    assert "TILTLAB_MAX_BODY_BYTES" in problem["detail"] and problem["status"] == 413
    assert sent < 2 * MIB, f"{sent} bytes were taken before the answer"
    # A body without a length (chunked) is counted as it comes and refused once past the limit.
    head = (
        b"POST /calibrations HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        b"Transfer-Encoding: chunked\r\n\r\n"
    )
    chunk = b"10000\r\n" + b"0" * 65536 + b"\r\n"
    answer, sent = response_while_sending(daemon.port, head, chunk, 2 * MIB)
    status, headers, problem = parse_problem(answer)
    assert status == 413 and headers["content-type"] == "application/problem+json", answer[:300]
    assert MIB < sent < 2 * MIB
    # The daemon's memory did not take the bodies (a read body would be a GiB).
    assert daemon.rss_kb("VmHWM") - peak_before < 64 * 1024, (peak_before, daemon.rss_kb("VmHWM"))
    assert daemon.rss_kb("VmRSS") - rss_before < 64 * 1024, (rss_before, daemon.rss_kb("VmRSS"))
    # Below the limit a body is read and judged as before (the token first).
    r = httpx.post(
        f"{daemon.base}/calibrations", content=b"{}", headers={"Content-Type": "application/json"}
    )
    assert r.status_code == 401
    h = {"Authorization": f"Bearer {daemon.token}"}
    r = httpx.post(f"{daemon.base}/calibrations", json={"procedure": "x" * (2 * MIB)}, headers=h)
    assert r.status_code == 413 and "TILTLAB_MAX_BODY_BYTES" in r.json()["detail"]


def _every_route(daemon: Daemon) -> list[tuple[str, str]]:
    h = {"Authorization": f"Bearer {daemon.token}"}
    spec = httpx.get(f"{daemon.base}/openapi.json", headers=h, timeout=30).json()
    routes = []
    for path, ops in spec["paths"].items():
        concrete = "/".join("1" if part.startswith("{") else part for part in path.split("/"))
        routes += [
            (method.upper(), concrete)
            for method in ops
            if method in ("get", "post", "put", "patch", "delete")
        ]
    return routes


async def _stream(
    url: str, *, subprotocol: str | None = None, messages: int = 2
) -> tuple[list[dict], str | None]:
    kwargs = {"subprotocols": [subprotocol]} if subprotocol else {}
    async with connect(url, **kwargs) as ws:  # type: ignore[arg-type]
        got = [json.loads(await asyncio.wait_for(ws.recv(), 30)) for _ in range(messages)]
        return got, ws.subprotocol


async def _closed_with(url: str, subprotocol: str) -> tuple[int, str]:
    async with connect(url, subprotocols=[subprotocol]) as ws:  # type: ignore[list-item]
        with pytest.raises(ConnectionClosed):
            while True:
                await asyncio.wait_for(ws.recv(), 60)
        return ws.close_code or 0, ws.close_reason or ""


def test_no_token_in_the_log_of_a_session_on_every_route_and_both_streams(daemon: Daemon) -> None:
    h = {"Authorization": f"Bearer {daemon.token}"}
    ws = daemon.base.replace("http", "ws", 1)
    routes = _every_route(daemon)
    assert len(routes) > 20
    with httpx.Client(base_url=daemon.base, headers=h, timeout=60) as client:
        job = client.post(
            "/calibrations",
            json={
                "procedure": "stage-grid",
                "method": "kinematic",
                "grid": {"x_deg": [-1.0, 1.0], "y_deg": [-1.0, 1.0], "n_x": 3, "n_y": 3},
                "samples_per_point": 4,
                "settle": {"tolerance_deg": 0.005, "window_s": 0.5, "timeout_s": 600},
            },
        )
        assert job.status_code == 202, job.text
        job_id = job.json()["id"]
        for method, path in routes:
            # a client may put its token in the query too: the access log prints queries
            r = client.request(
                method,
                path,
                params={"token": daemon.token},
                json={} if method in ("POST", "PUT", "PATCH") else None,
            )
            assert r.status_code != 500, (method, path, r.status_code, r.text)

    async def streams() -> None:
        # both streams, with the token in the query (as before) and as the subprotocol (echoed in
        # the accept)
        msgs, chosen = await _stream(f"{ws}/ws/readings?token={daemon.token}&history_s=1")
        assert msgs[0]["type"] == "snapshot" and chosen is None
        msgs, chosen = await _stream(
            f"{ws}/ws/readings?history_s=1", subprotocol=f"bearer.{daemon.token}"
        )
        assert msgs[0]["type"] == "snapshot" and msgs[1]["seq"] == 1
        assert chosen == f"bearer.{daemon.token}"
        msgs, chosen = await _stream(f"{ws}/ws/jobs/{job_id}?token={daemon.token}", messages=1)
        assert msgs[0]["type"] == "snapshot" and msgs[0]["job"]["id"] == job_id
        msgs, chosen = await _stream(
            f"{ws}/ws/jobs/{job_id}", subprotocol=f"bearer.{daemon.token}", messages=1
        )
        assert msgs[0]["type"] == "snapshot" and chosen == f"bearer.{daemon.token}"
        code, reason = await _closed_with(
            f"{ws}/ws/readings", "bearer.tl_not_a_token_at_all_000000"
        )
        assert code == 1008 and reason.startswith("token:")

    asyncio.run(streams())
    httpx.post(f"{daemon.base}/stage/stop", headers=h, timeout=30)
    log = daemon.log.read_text()
    assert "/ws/readings?token=[redacted]" in log and "GET /tilt?token=[redacted]" in log, log[
        -2000:
    ]
    assert daemon.token not in log
    assert daemon.token.removeprefix("tl_")[:16] not in log  # not even a part of it


def test_revoking_a_token_ends_its_open_streams(tmp_path: Path) -> None:
    with logged_daemon(tmp_path) as d:
        ws = d.base.replace("http", "ws", 1)
        h = {"Authorization": f"Bearer {d.token}"}
        r = tiltlab_cli(d.env, "token", "create", "--name", "watcher", "--scopes", "read")
        assert r.returncode == 0, r.stderr
        watcher = r.stdout.strip()
        job = httpx.post(
            f"{d.base}/calibrations",
            headers=h,
            timeout=30,
            json={
                "procedure": "stage-grid",
                "method": "kinematic",
                "grid": {"x_deg": [-1.0, 1.0], "y_deg": [-1.0, 1.0], "n_x": 3, "n_y": 3},
                "samples_per_point": 400,
                "settle": {"tolerance_deg": 0.005, "window_s": 0.5, "timeout_s": 600},
            },
        )
        assert job.status_code == 202, job.text

        async def watch() -> list[tuple[int, str]]:
            opened = asyncio.Event()
            count = 0

            async def one(url: str) -> tuple[int, str]:
                nonlocal count
                async with connect(url, subprotocols=[f"bearer.{watcher}"]) as s:  # type: ignore[list-item]
                    await asyncio.wait_for(s.recv(), 30)
                    count += 1
                    if count == 2:
                        opened.set()
                    with pytest.raises(ConnectionClosed):
                        while True:
                            await asyncio.wait_for(s.recv(), 60)
                    return s.close_code or 0, s.close_reason or ""

            tasks = [
                asyncio.create_task(one(f"{ws}/ws/readings?history_s=1")),
                asyncio.create_task(one(f"{ws}/ws/jobs/{job.json()['id']}")),
            ]
            await asyncio.wait_for(opened.wait(), 60)
            # revoked from another process: the daemon learns it from its database
            revoked = await asyncio.to_thread(tiltlab_cli, d.env, "token", "revoke", "watcher")
            assert revoked.returncode == 0, revoked.stderr
            return list(await asyncio.gather(*tasks))

        for code, reason in asyncio.run(watch()):
            assert code == 1008 and reason.startswith("token: revoked"), (code, reason)
        # the other token's streams go on
        msgs, _ = asyncio.run(
            _stream(f"{ws}/ws/readings?history_s=1", subprotocol=f"bearer.{d.token}")
        )
        assert msgs[0]["type"] == "snapshot"
        httpx.post(f"{d.base}/calibrations/{job.json()['id']}/cancel", headers=h, timeout=30)
