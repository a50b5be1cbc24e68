"""A full disk fails cleanly: on a small file system of its own (a tmpfs; skipped, saying so, where
this machine may not mount one), a daemon whose data directory fills while a job runs stops the job,
shows it failed with the cause although the cause cannot be stored, frees the bench, says `/ready`
503 naming the disk, answers writes 507 naming it (never 500), stores the job's end once space is
freed, and resumes the job to its end.
"""

from __future__ import annotations

import contextlib
import errno
import os
import sqlite3
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.helpers.processes import spawn
from tests.helpers.running_service import free_port
from tests.helpers.waiting import eventually

DISK_MB = 32
MIN_FREE_MB = 4
BODY = {
    "procedure": "stage-grid",
    "method": "kinematic",
    "samples_per_point": 20,
    "validation": {"n_points": 2},
    "grid": {"x_deg": [-2, 2], "y_deg": [-2, 2], "n_x": 5, "n_y": 5},
    "settle": {"tolerance_deg": 0.005, "window_s": 0.5, "timeout_s": 120},
}


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    mount = tmp_path / "disk"
    mount.mkdir()
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={DISK_MB}m", "tmpfs", str(mount)],
        capture_output=True,
        text=True,
    )
    if r.returncode != 0:
        pytest.skip(
            "a small file system cannot be mounted here (mount -t tmpfs: "
            f"{r.stderr.strip() or r.returncode}); the full-disk test needs one"
        )
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def _fill(folder: Path) -> Path:
    """A file taking every byte the file system has left."""
    filler = folder / "filler"
    with filler.open("wb", buffering=0) as f:
        for size in (1 << 20, 1 << 12, 1):
            while True:
                try:
                    if f.write(b"\0" * size) == 0:
                        break
                except OSError as exc:
                    assert exc.errno == errno.ENOSPC, exc
                    break
    return filler


def test_a_full_disk_fails_the_job_cleanly_and_it_resumes_once_space_is_freed(
    small_disk: Path,
) -> None:
    data = small_disk / "data"
    port = free_port()
    env = {
        **os.environ,
        "TILTLAB_DATA_DIR": str(data),
        "TILTLAB_SIM_SPEED": "20",
        "TILTLAB_SIM_TRANSPORT": "loopback",
        "TILTLAB_MIN_FREE_MB": str(MIN_FREE_MB),
    }
    log = small_disk.parent / "daemon.log"
    with log.open("wb") as out:
        proc = spawn(
            [sys.executable, "-m", "service", "serve", "--port", str(port)],
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    base = f"http://127.0.0.1:{port}"
    filler: Path | None = None
    try:
        eventually(
            lambda: httpx.get(f"{base}/health", timeout=2).status_code == 200,
            timeout_s=90,
            every_s=0.2,
            ignoring=(httpx.TransportError,),
            what="the daemon answering /health",
        )
        h = {"Authorization": "Bearer " + (data / "admin.token").read_text().strip()}
        with httpx.Client(base_url=base, headers=h, timeout=60) as c:
            assert c.get("/ready").status_code == 200
            r = c.post("/calibrations", json=BODY)
            assert r.status_code == 202, r.text
            job_id = r.json()["id"]
            eventually(
                lambda: c.get(f"/calibrations/{job_id}").json(),
                until=lambda j: j["progress"]["points_done"] >= 2,
                timeout_s=180,
                every_s=0.2,
                what="two points done",
            )

            filler = _fill(small_disk)  # the data directory's disk is full: not a byte left
            job = eventually(
                lambda: c.get(f"/calibrations/{job_id}").json(),
                until=lambda j: j["state"] != "running",
                timeout_s=180,
                every_s=0.2,
                what="the job no longer running",
            )
            assert job["state"] == "failed" and job["interrupted"] is True, job
            assert (
                "disk full" in job["error"]
                and str(data) in job["error"]
                and "resume" in job["error"]
            ), job
            # the cause is known, the disk took nothing
            assert "not stored yet" in job["error"], job
            bench = c.get("/benches").json()["benches"][0]
            assert bench["held_by"] is None, bench  # the bench is free
            health = c.get("/health")
            assert health.status_code == 200 and health.json()["status"] == "degraded"
            assert health.json()["jobs_not_stored"] == [job_id]
            ready = c.get("/ready")
            assert ready.status_code == 503, ready.text
            assert any(
                reason.startswith("disk full:") and str(data) in reason and "MB free" in reason
                for reason in ready.json()["reasons"]
            ), ready.json()
            for path, body in (
                (
                    "/orders",
                    {
                        "lims_order_id": "L-1",
                        "item_serial": "S-1",
                        "procedure": "stage-grid",
                        "method": "kinematic",
                        "customer": {"name": "Survey Ltd", "city": "Delft", "country_code": "NL"},
                    },
                ),
                ("/tokens", {"name": "lims", "scopes": ["read"]}),
                ("/calibrations", BODY),
            ):
                refused = c.post(path, json=body)
                assert refused.status_code == 507, (path, refused.status_code, refused.text)
                assert "disk full" in refused.json()["detail"], (path, refused.text)
            resumed = c.post(f"/calibrations/{job_id}/resume")
            # no room yet: the job waits, the cause stays
            assert resumed.status_code == 507, resumed.text

            filler.unlink()  # space again: the job's end is stored, then it resumes
            filler = None
            eventually(
                lambda: c.get("/health").json(),
                until=lambda body: body["jobs_not_stored"] == [],
                timeout_s=180,
                every_s=0.2,
                what="the job's end stored",
            )
            with contextlib.closing(
                sqlite3.connect(f"file:{data / 'tiltlab.db'}?mode=ro", uri=True)
            ) as db:
                state, interrupted, reason = db.execute(
                    "SELECT state, interrupted, failure_reason FROM calibration_jobs WHERE id = ?",
                    (job_id,),
                ).fetchone()
            assert state == "failed" and interrupted == 1 and reason.startswith("disk full"), (
                state,
                interrupted,
                reason,
            )
            assert c.get("/ready").status_code == 200
            resumed = c.post(f"/calibrations/{job_id}/resume")
            assert resumed.status_code == 202, resumed.text
            job = eventually(
                lambda: c.get(f"/calibrations/{job_id}").json(),
                until=lambda j: j["state"] in ("succeeded", "failed", "cancelled"),
                timeout_s=600,
                every_s=0.2,
                what="the resumed job ended",
            )
            assert job["state"] == "succeeded", job
    finally:
        if filler is not None:
            filler.unlink(missing_ok=True)
        proc.terminate()
        proc.wait(timeout=60)
    verified = subprocess.run(
        [sys.executable, "-m", "service", "db", "verify"],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert verified.returncode == 0, verified.stdout + verified.stderr
