"""The live stream of one calibration job: its state and progress on every change, its points as
they are measured, then its end. Woken by the job manager's events (service/jobs/events.py), it
reads the job once per change; a slow safety re-read covers a change made by another process."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncGenerator, Callable, Mapping
from typing import Literal, TypedDict, cast

from service.io.json_value import JSONObject, members
from service.jobs.events import JobEvents
from service.jobs.manager import WAITING_FOR_DATABASE
from service.storage.models import CalibrationJob, SettledPoint
from service.storage.outage import unreachable
from service.storage.store import JobsRepo, PointsRepo

ENDED = frozenset({"succeeded", "failed", "cancelled"})
SAFETY_REREAD_S = 5.0  # real seconds between re-reads when no event came


class PointMeans(TypedDict):
    """One instrument's robust means at a point, as the stream shows them (degrees, °C)."""

    x_deg: float
    y_deg: float
    z_deg: float | None
    x_std_deg: float | None
    y_std_deg: float | None
    z_std_deg: float | None
    n_samples: int
    temp_c: float | None


# A job's point in its stream: "index", the commanded stage angles "x_deg", "y_deg" (None without a
# stage or a second axis), and under each role of the job's instruments (its keys vary by job)
# their PointMeans.
JobPoint = dict[str, int | float | PointMeans | None]


class JobSnapshotMessage(TypedDict):
    """A job stream's first message: the job as GET /calibrations/{id} answers it, its points so
    far."""

    type: Literal["snapshot"]
    job: JSONObject
    points: list[JobPoint]


class JobPointMessage(TypedDict):
    """A point of the job, once every instrument of the job has its mean there."""

    type: Literal["point"]
    point: JobPoint


class JobChangeMessage(TypedDict):
    """The job again, when its state, progress, error, record or validation changed; or its end
    (the last message), the job as it ended."""

    type: Literal["job", "end"]
    job: JSONObject


# One message of a job's stream, before the stream numbers it (`seq`).
JobStreamMessage = JobSnapshotMessage | JobPointMessage | JobChangeMessage


def point_index(point: JobPoint) -> int:
    """A job point's index (an int by construction in `job_points`)."""
    return cast(int, point["index"])


def job_points(
    points: PointsRepo, job: CalibrationJob, have: frozenset[int] | set[int] | None = None
) -> list[JobPoint]:
    """The job's points measured so far (every instrument of the job has its mean), by index,
    leaving out those in `have`: {"index", "x_deg", "y_deg" (commanded stage angles; y null on a
    one-axis procedure), and per role {"x_deg", "y_deg", "z_deg", "x_std_deg", "y_std_deg",
    "z_std_deg", "n_samples", "temp_c"} of the robust means}."""
    roles = _roles_of(job)
    by_point: dict[int, JobPoint] = {}
    # Points are measured in index order: only those from the first one not yet had are read, so a
    # follower's reads stay small however long the job (not all its points on every change).
    for settled_point in points.settled_points(job.id, from_point=_first_missing(have)):
        if have is not None and settled_point.point in have:
            continue
        role = roles.get(settled_point.device_id)
        if role is None:
            continue
        pt = by_point.setdefault(
            settled_point.point,
            {
                "index": settled_point.point,
                "x_deg": settled_point.cmd_x_deg,
                "y_deg": settled_point.cmd_y_deg,
            },
        )
        pt[role] = _means_of(settled_point)
    return [
        pt for i, pt in sorted(by_point.items()) if all(needed in pt for needed in roles.values())
    ]


def _first_missing(have: frozenset[int] | set[int] | None) -> int:
    """The first point index not in `have` (0 when nothing is had yet)."""
    return 0 if have is None else next(i for i in range(len(have) + 1) if i not in have)


def _roles_of(job: CalibrationJob) -> dict[int, str]:
    """The role of each instrument of the job, by device id (a job that names none: its device,
    as the measurement sensor)."""
    roles = {
        dev: role
        for role, dev in (job.parameters or {}).get("device_ids", {}).items()
        if dev is not None
    }
    return roles or {job.device_id: "measurement_sensor"}


def _means_of(settled_point: SettledPoint) -> PointMeans:
    """One instrument's robust means at a point, as the stream shows them."""
    return {
        "x_deg": settled_point.ch_x_mean,
        "y_deg": settled_point.ch_y_mean,
        "z_deg": settled_point.ch_z_mean,
        "x_std_deg": settled_point.ch_x_std,
        "y_std_deg": settled_point.ch_y_std,
        "z_std_deg": settled_point.ch_z_std,
        "n_samples": settled_point.n_samples,
        "temp_c": settled_point.temp_c_mean,
    }


async def job_messages(
    stored_jobs: JobsRepo,
    points_repo: PointsRepo,
    events: JobEvents,
    job_id: int,
    body: Callable[[CalibrationJob], JSONObject],
) -> AsyncGenerator[JobStreamMessage, None]:
    """The messages of one job's stream without seq, ending with its `end` (UnknownEntity if no such
    job). `body` is the job as the API serialises it, read through, not looked into (but for its
    progress's phase)."""
    event = events.subscribe(job_id)
    try:
        # database reads off the event loop
        job = await asyncio.to_thread(stored_jobs.get_job, job_id)
        # the job's body reads its record: off the event loop too
        last = await asyncio.to_thread(body, job)
        points = await asyncio.to_thread(job_points, points_repo, job)
        have = {point_index(point) for point in points}
        yield {"type": "snapshot", "job": last, "points": points}
        while job.state not in ENDED:
            with_timeout = asyncio.wait_for(event.wait(), SAFETY_REREAD_S)
            try:
                await with_timeout
            except TimeoutError:
                pass
            event.clear()
            try:
                job = await asyncio.to_thread(stored_jobs.get_job, job_id)
                points = await asyncio.to_thread(job_points, points_repo, job, frozenset(have))
                now = await asyncio.to_thread(body, job)
            except Exception as exc:
                if not unreachable(exc):
                    raise
                # The database away: the job's last state, its phase saying what it waits for (its
                # next step waits too); the stream goes on and reads again on the next change or
                # re-read.
                waiting: JSONObject = {
                    **last,
                    "progress": {**members(last.get("progress")), "phase": WAITING_FOR_DATABASE},
                }
                if _changed(last, waiting):
                    yield {"type": "job", "job": waiting}
                last = waiting
                continue
            for point in points:
                have.add(point_index(point))
                yield {"type": "point", "point": point}
            if _changed(last, now):
                yield {"type": "job", "job": now}
            last = now
        yield {"type": "end", "job": last}
    finally:
        events.unsubscribe(job_id, event)


def _changed(a: Mapping[str, object], b: Mapping[str, object]) -> bool:
    """State, progress, error, record or validation differ (not only the update time)."""
    keys = (
        "state",
        "interrupted",
        "progress",
        "error",
        "record",
        "validation",
        "started_utc",
        "finished_utc",
    )
    return any(a.get(k) != b.get(k) for k in keys)
