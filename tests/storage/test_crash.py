"""kill -9 of a process streaming samples: the database stays consistent, the loss stays within the
bound."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import sqlalchemy as sa

from service.storage import Store
from tests.helpers.processes import spawn

CAPACITY, BATCH = 8000, 2000
HANDED = 40_000
HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]


@pytest.mark.slow
def test_sigkill_mid_stream(store: Store, device, db_url: str) -> None:  # type: ignore[no-untyped-def]
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
    }
    argv = [db_url, str(device.id), str(CAPACITY), str(BATCH), str(HANDED)]
    child = spawn(
        [sys.executable, str(HERE / "crash_writer.py"), *argv],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert child.stdout is not None
        bound = int(child.stdout.readline().split()[1])
        assert bound == CAPACITY + BATCH
        # exact: nothing more is handed over after this
        handed = int(child.stdout.readline().split()[1])
        child.send_signal(signal.SIGKILL)  # while its writer thread works through a full queue
    finally:
        child.kill()
        child.wait(timeout=30)
    assert child.returncode == -signal.SIGKILL
    assert handed == HANDED

    with store.engine.connect() as conn:
        if store.engine.dialect.name == "sqlite":
            assert conn.exec_driver_sql("PRAGMA integrity_check").scalar() == "ok"
            assert conn.exec_driver_sql("PRAGMA foreign_key_check").all() == []
        rows, distinct, lo, hi = conn.execute(
            sa.text("SELECT count(*), count(DISTINCT ch_x), min(ch_x), max(ch_x) FROM samples")
        ).one()
    # Committed samples are exactly the oldest ones handed over: no duplicates, no holes, nothing
    # invented.
    assert rows == distinct and 0 < rows <= handed
    assert (lo, hi) == (0.0, float(rows - 1))
    lost = handed - rows
    print(f"handed over {handed}, committed {rows}, lost {lost} (bound {bound})")
    assert lost <= bound
