"""kill -9 of a process streaming samples: the database stays consistent, the loss stays within the bound."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import sqlalchemy as sa

from service.storage import Store

CAPACITY, BATCH = 8000, 2000
HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]


@pytest.mark.slow
def test_sigkill_mid_stream(store: Store, device, db_url: str) -> None:  # type: ignore[no-untyped-def]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    child = subprocess.Popen(
        [sys.executable, str(HERE / "crash_writer.py"), db_url, str(device.id), str(CAPACITY), str(BATCH)],
        stdout=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    try:
        assert child.stdout is not None
        bound = int(child.stdout.readline().split()[1])
        assert bound == CAPACITY + BATCH
        handed = 0
        for line in child.stdout:  # kill well into the stream, with the queue busy
            handed = int(line)
            if handed >= 5 * CAPACITY:
                break
        child.send_signal(signal.SIGKILL)
        for line in child.stdout:  # what it still reported before it died
            handed = int(line)
    finally:
        child.kill()
        child.wait(timeout=30)
    assert child.returncode == -signal.SIGKILL

    with store.engine.connect() as conn:
        if store.engine.dialect.name == "sqlite":
            assert conn.exec_driver_sql("PRAGMA integrity_check").scalar() == "ok"
            assert conn.exec_driver_sql("PRAGMA foreign_key_check").all() == []
        rows, distinct, lo, hi = conn.execute(sa.text(
            "SELECT count(*), count(DISTINCT ch_x), min(ch_x), max(ch_x) FROM samples")).one()  # fmt: skip
    # Committed samples are exactly the oldest ones handed over: no duplicates, no holes.
    assert rows == distinct and rows > 0
    assert (lo, hi) == (0.0, float(rows - 1))
    # At most one chunk can have been handed over after the last line it printed.
    assert rows <= handed + 500
    lost = handed - rows
    print(f"handed over >= {handed}, committed {rows}, lost <= {max(lost, 0)} (bound {bound})")
    assert lost <= bound
