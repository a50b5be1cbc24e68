"""What is left of the settling transient in the points a job stored: the simulator's truth, which
no bench shows (a reading is the table plus the transient plus noise).

The simulated world keeps what the transient added to its readings while `transient_log` holds a
list (`World.transient_log`); a job's stored samples say when each point was read. Used by
benchmarks/settled_transient.py and the tests of the settling rules.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.jobs.procedure import bench_epoch
from service.storage.samples import job_samples

TransientLog = list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]


def transient_in_points(
    app: Any, job_id: int, log: TransientLog, role: str = "reference_sensor"
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per stored point of the job (in point order): the transient (stage x, stage y, deg) averaged
    over the role's stored readings of it, and how many readings that is. Samples are stamped in
    POSIX seconds from bench seconds (service.jobs.procedure.bench_epoch); the same mapping taken
    back here."""
    bench = app.state.bench
    clock = bench.clock
    epoch = bench_epoch(bench)(0.0)  # POSIX seconds of bench second 0
    at = np.concatenate([entry[0] for entry in log])
    order = np.argsort(at, kind="stable")
    at = at[order]
    stage_x = np.concatenate([entry[1] for entry in log])[order]
    stage_y = np.concatenate([entry[2] for entry in log])[order]
    device = bench.device_ids[role]
    with app.state.engine.connect() as conn:
        samples = [s for s in job_samples(conn, job_id) if s.device_id == device]
    by_point: dict[int, list[float]] = {}
    for sample in samples:
        bench_s = clock.bench_seconds(sample.t_s - epoch)
        by_point.setdefault(int(sample.point or 0), []).append(bench_s)
    bias, counts = [], []
    for point in sorted(by_point):
        t = np.asarray(by_point[point])
        bias.append([np.interp(t, at, stage_x).mean(), np.interp(t, at, stage_y).mean()])
        counts.append(len(t))
    return np.asarray(bias, dtype=float), np.asarray(counts, dtype=float)
