"""A job's database writes: one measured point (its raw samples and settled means), and the
worker-thread call every write of a job goes through."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any, TypeVar

from service.storage.samples import Sample
from service.storage.store import Store
from service.storage.store.hashing import SettledPointFields

log = logging.getLogger("tiltlab.jobs")
T = TypeVar("T")
_writes_in_flight = 0


def writes_in_flight() -> int:
    """Job writes handed to worker threads and not yet stored (the daemon's metrics show it)."""
    return _writes_in_flight


def store_point(
    store: Store,
    job_id: int,
    index: int,
    samples: list[Sample],
    settled_by_device: dict[int, SettledPointFields],
) -> None:
    """Blocking (database): call through `write_in_thread`. The point's raw samples and settled
    means in one transaction (see `PointsRepo.add_measured_point`): a failed write leaves nothing,
    and a repeat after a COMMIT whose answer was lost writes nothing twice."""
    store.points.add_measured_point(job_id, index, samples, settled_by_device, actor="daemon")


async def write_in_thread(write: Callable[..., T], /, *args: Any, **kwargs: Any) -> T:
    """A job's database write in a worker thread, run to its end even if the job is cancelled
    meanwhile. A thread cannot be stopped: a cancellation that left it running would let whoever
    cancelled the job (and waited for it) read the job before the write landed. The cancellation
    waits for the write, then goes on."""
    global _writes_in_flight
    _writes_in_flight += 1
    work = asyncio.ensure_future(asyncio.to_thread(write, *args, **kwargs))
    work.add_done_callback(_written)
    try:
        return await asyncio.shield(work)
    except asyncio.CancelledError:
        await asyncio.wait({work})
        if not work.cancelled() and work.exception() is not None:
            log.warning(
                "a job's database write failed while the job was being cancelled: %s",
                work.exception(),
            )
        raise


def _written(_: object) -> None:
    global _writes_in_flight
    _writes_in_flight -= 1
