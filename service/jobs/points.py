"""Storing one measured point of a job: its raw samples and its settled means, in a worker thread."""

from __future__ import annotations

from service.storage.daemon_jobs import DaemonStore
from service.storage.samples import Sample, write_samples


def store_point(store: DaemonStore, job_id: int, index: int, samples: list[Sample],
                settled_by_device: dict[int, dict]) -> None:
    """Blocking (database): call through `asyncio.to_thread`. A point half stored when the daemon
    was killed keeps its stored half; only the devices it lacks are added."""
    write_samples(store.engine, samples)
    have = {p.device_id for p in store.settled_points(job_id) if p.point == index}
    for device_id, point in settled_by_device.items():
        if device_id not in have:
            store.add_settled_points(job_id, device_id, [point], actor="daemon")
