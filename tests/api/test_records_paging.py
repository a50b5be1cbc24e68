"""`GET /records` pages, and reading every page in a loop does not hold `/tilt` hostage: with 2,000
records (each with its model, as a job stores it), `/tilt` answers every request while a client
reads page after page, and its p99 then stays within 10x of its p99 idle in the same run. The pages
are made and serialised in a request thread, never on the event loop.

Why 10x: `GET /records` unpaged (1,600 records decoded per request) held `/tilt`'s p99 at 66x its
idle figure (231 ms against 3.5 ms); paged and made in a thread it is 2-3x, and a whole suite run
beside two busy loops reached 3.09x. The bound sits between the fault and the machine's scheduling
noise.

Idle and busy are measured in turns (three of each), so a load that comes and goes on the machine
falls on both. The reading client runs at a lower CPU priority (nice 5): a LIMS runs on a machine
of its own, and here it would otherwise take one of the daemon's two cores for its own JSON
decoding, which is not the daemon's latency. The figures are printed (`pytest -s`); docs/api.md
quotes them.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from service.config import Settings
from service.storage.engine import make_engine
from service.storage.store import Store
from tests.helpers.daemon import admin_headers, make_client, wait_job
from tests.helpers.diagnosis import SMALL_BODY
from tests.helpers.logged_daemon import logged_daemon
from tests.helpers.processes import spawn

READER = """
import pathlib, sys, httpx
base, token, stop = sys.argv[1], sys.argv[2], pathlib.Path(sys.argv[3])
read = 0
with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {token}"}, timeout=120) as c:
    while not stop.exists():
        cursor = None
        while not stop.exists():
            page = {"limit": 50, **({"cursor": cursor} if cursor else {})}
            body = c.get("/records", params=page).json()
            read += len(body["records"])
            if (cursor := body["next_cursor"]) is None:
                break
print(read)
"""
RECORDS = 2000
SAMPLES = 300  # /tilt requests in each turn
TURNS = 3


@pytest.fixture(scope="module")
def many_records(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data directory with 2,000 stage records: one from a job, the rest versions of it."""
    data = tmp_path_factory.mktemp("records")
    with make_client(data) as client:
        h = admin_headers(data)
        r = client.post("/calibrations", headers=h, json=SMALL_BODY)
        assert r.status_code == 202, r.text
        job = wait_job(client, r.json()["id"], h)
        assert job["state"] == "succeeded", job
    engine = make_engine(Settings(data_dir=data).database_url)
    store = Store(engine)
    first = store.records.get_record(job["record"]["id"])
    for _ in range(RECORDS - 1):
        store.records.add_record(
            first.device_id,
            first.kind,
            first.method,
            first.model,
            operator=first.operator,
            validation=first.validation,
            temp_c=first.temp_c,
            job_id=first.job_id,
            raw_data={"fit_points": first.raw_data["fit_points"]},
        )
    engine.dispose()
    return data


def _tilt_latencies(base: str, token: str) -> list[float]:
    out = []
    with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {token}"}, timeout=60) as c:
        for _ in range(SAMPLES):
            t0 = time.perf_counter()
            assert c.get("/tilt").status_code == 200
            out.append(time.perf_counter() - t0)
            time.sleep(0.005)
    return out


def test_records_page_and_reading_them_all_leaves_tilt_alone(
    many_records: Path, tmp_path: Path
) -> None:
    data = tmp_path / "data"
    shutil.copytree(many_records, data)
    with logged_daemon(tmp_path, TILTLAB_DATA_DIR=str(data), TILTLAB_SIM_TRANSPORT="loopback") as d:
        auth = {"Authorization": f"Bearer {d.token}"}
        with httpx.Client(base_url=d.base, headers=auth, timeout=120) as c:
            ids, cursor, pages = [], None, 0
            while True:
                page = c.get(
                    "/records", params={"limit": 50, **({"cursor": cursor} if cursor else {})}
                )
                assert page.status_code == 200, page.text
                body = page.json()
                ids += [r["id"] for r in body["records"]]
                pages += 1
                cursor = body["next_cursor"]
                if cursor is None:
                    break
        assert (
            len(ids) == len(set(ids)) == RECORDS
            and ids == sorted(ids, reverse=True)
            and pages == RECORDS // 50 + 1
        )
        _tilt_latencies(d.base, d.token)  # warm: the token known, the route's path taken once
        idle: list[float] = []
        busy: list[float] = []
        read = []
        for turn in range(TURNS):
            idle += _tilt_latencies(d.base, d.token)
            # the reader in a process of its own: decoding its pages must not hold the measuring
            # client's interpreter
            stop = tmp_path / f"stop-{turn}"
            reader = spawn(
                ["nice", "-n", "5", sys.executable, "-c", READER, d.base, d.token, str(stop)],
                stdout=subprocess.PIPE,
                text=True,
            )
            try:
                time.sleep(1.0)
                busy += _tilt_latencies(d.base, d.token)
            finally:
                stop.touch()
                out, _ = reader.communicate(timeout=120)
            read.append(int(out.split()[-1]))
    assert sum(read) >= RECORDS and min(read) > 0, f"the reader got through {read} records"
    base99, busy99 = np.percentile(idle, 99), np.percentile(busy, 99)
    figures = (
        f"/tilt idle p99 {base99 * 1e3:.2f} ms; while reading every page p99 "
        f"{busy99 * 1e3:.2f} ms ({busy99 / base99:.2f}x; {sum(read)} records read in {TURNS} turns)"
    )
    print(figures)  # every /tilt answered 200 while reading: _tilt_latencies asserts it
    assert busy99 <= 10 * base99, figures
