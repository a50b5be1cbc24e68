"""Several daemons, one database: processes appending at once keep every chain whole and lose
nothing.

Four processes (not threads: each has its own engine and connection pool, as each daemon of a
fleet does) append record versions (one chain they all contend for, one of their own), approvals
(one global chain) and audit events for a while. Afterwards every row a writer saw committed is
in the database, and `db verify`'s checks find every hash and chain link sound.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import sqlalchemy as sa

from service.storage.store import Store
from service.storage.verify import verify
from tests.helpers.processes import spawn
from tests.helpers.storage import count

WRITER = Path(__file__).with_name("fleet_writer.py")
WRITERS = 4


def _seconds(backend: str) -> float:
    """How long the writers run: 30 s on PostgreSQL (the fleet's store), 8 s on SQLite (one
    PC's)."""
    default = "30" if backend == "postgresql" else "8"
    return float(os.environ.get("TILTLAB_TEST_FLEET_WRITE_S", default))


def test_four_processes_appending_at_once_keep_every_chain_and_lose_nothing(
    engine: sa.Engine, db_url: str, backend: str
) -> None:
    store = Store(engine)
    shared = store.devices.add_device("fleet-writer", "shared", "measurement_sensor", actor="test")
    records0, approvals0, audit0 = (
        count(engine, t) for t in ("calibration_records", "record_approvals", "audit_events")
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    seconds = _seconds(backend)
    procs = [
        spawn(
            [sys.executable, str(WRITER), db_url, f"node{n}", str(shared.id), str(seconds)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for n in range(WRITERS)
    ]
    results = []
    for proc in procs:
        out, err = proc.communicate(timeout=seconds + 120)
        assert proc.returncode == 0, err[-2000:]
        results.append(json.loads(out.strip().splitlines()[-1]))

    made = {key: sum(r[key] for r in results) for key in results[0]}
    # every writer got its turns
    assert all(r["records"] > 0 and r["benches"] > 0 for r in results), results
    assert count(engine, "calibration_records") - records0 == made["records"]
    assert count(engine, "record_approvals") - approvals0 == made["approvals"]
    # each writer's own device, each record version, each approval and each bench left one audit
    # event
    assert (
        count(engine, "audit_events") - audit0
        == WRITERS + made["records"] + made["approvals"] + made["benches"]
    )

    versions = sorted(r.version for r in store.records.of_device(shared.id))
    assert versions == list(range(1, len(versions) + 1))  # the contended chain: no gap, no fork
    assert len(versions) == made["records"] // 2

    report = verify(engine)
    assert report.ok, "\n".join(report.lines())
