"""Child process of the many-writers test: one daemon's worth of appends to a shared database.

Usage: python fleet_writer.py URL NAME SHARED_DEVICE_ID SECONDS (the repository on PYTHONPATH)
For SECONDS it appends, in turn: a record version to the device all writers share (one hash
chain contended by every process), a record version to a device of its own, an approval of a
draft some writer made (the global approval chain), and an audit event (a bench registration).
Each append it saw committed is counted; at the end it prints one JSON line of those counts,
which the parent compares with the rows the database holds.
"""

from __future__ import annotations

import json
import sys
import time

from service.storage import make_engine
from service.storage.errors import ConflictError
from service.storage.store import Store
from tests.helpers.storage import MODEL
from tests.helpers.waiting import eventually


def main() -> None:
    url, name, shared_device, seconds = (
        sys.argv[1],
        sys.argv[2],
        int(sys.argv[3]),
        float(sys.argv[4]),
    )
    engine = make_engine(url)
    store = Store(engine)
    own = store.devices.add_device("fleet-writer", f"{name}-own", "measurement_sensor", actor=name)
    counts = {"records": 0, "approvals": 0, "benches": 0, "conflicts": 0}
    started = time.monotonic()
    turn = 0

    def one_turn() -> bool:
        """One turn of appends; True, and none made, once SECONDS have passed."""
        nonlocal turn
        if time.monotonic() - started >= seconds:
            return True
        turn += 1
        shared = store.records.add_record(shared_device, "scale", "linear", MODEL, operator=name)
        store.records.add_record(own.id, "scale", "linear", MODEL, operator=name)
        counts["records"] += 2
        # another writer may decide the same draft first: a decision is final, the loser is refused
        try:
            store.approvals.decide(
                shared.id - 1 if shared.id > 1 else shared.id,
                decision="approve",
                meaning="approval",
                note="",
                actor=f"{name}-reviewer",
            )
            counts["approvals"] += 1
        except ConflictError:
            counts["conflicts"] += 1
        store.devices.ensure_bench(f"{name}-bench-{turn}", actor=name)
        counts["benches"] += 1
        return False

    # bounded as the parent bounds this process: SECONDS and 120 s for a last turn held up
    eventually(one_turn, timeout_s=seconds + 120, every_s=0, what=f"{seconds:g} s of appends")
    engine.dispose()
    print(json.dumps(counts), flush=True)


if __name__ == "__main__":
    main()
