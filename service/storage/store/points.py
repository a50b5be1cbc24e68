"""Settled grid points of a job: added directly or averaged from the job's raw samples."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session

from service.errors import InputError
from service.storage.canonical import sha256_hex
from service.storage.errors import IllegalTransition
from service.storage.models import JobState, SettledPoint
from service.storage.models import Sample as SampleRow
from service.storage.samples import Sample, insert_samples_once
from service.storage.store.checks import require_finite, require_number
from service.storage.store.database import Database
from service.storage.store.hashing import (
    POINT_FIELDS,
    POINT_REQUIRED,
    SAMPLE_FIELDS,
    SettledPointFields,
    point_content,
    points_sha256,
    samples_sha256,
)
from service.storage.store.lookups import device_in, job_in


class PointsRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def add_settled_points(
        self, job_id: int, device_id: int, points: Sequence[Mapping[str, object]], *, actor: str
    ) -> list[SettledPoint]:
        with self._db.transaction() as session:
            return self._add(session, job_id, device_id, points, actor)

    def add_measured_point(
        self,
        job_id: int,
        index: int,
        samples: Sequence[Sample],
        settled_by_device: Mapping[int, SettledPointFields],
        *,
        actor: str,
    ) -> None:
        """A point a job measured, stored whole or not at all: its raw samples and every device's
        settled means in one transaction, so a write that fails (a full disk) leaves nothing of it
        and the point is measured again whole on resume. A device whose settled point is already
        stored at this index (a point half stored by an earlier version of the daemon) keeps it
        and its samples: the new samples of that device are not added to them, which would break
        the hash the stored point holds. Safe to repeat after a COMMIT whose answer was lost."""
        with self._db.transaction() as session:
            have = set(
                session.scalars(
                    sa.select(SettledPoint.device_id).where(
                        SettledPoint.job_id == job_id, SettledPoint.point == index
                    )
                )
            )
            insert_samples_once(
                session.connection(), [sample for sample in samples if sample.device_id not in have]
            )
            for device_id, point in settled_by_device.items():
                if device_id not in have:
                    self._add(session, job_id, device_id, [point], actor)

    def _add(
        self,
        session: Session,
        job_id: int,
        device_id: int,
        points: Sequence[Mapping[str, object]],
        actor: str,
    ) -> list[SettledPoint]:
        job = job_in(session, job_id)
        device_in(session, device_id)
        if job.state != JobState.RUNNING:
            raise IllegalTransition(
                f"job {job_id} is {job.state}; settled points are added while it runs"
            )
        rows: list[SettledPoint] = []
        for i, given in enumerate(points):
            values = _point_values(i, given)
            values["samples_sha256"] = point_samples_sha256(
                session, job_id, device_id, values["point"]
            )
            rows.append(SettledPoint(job_id=job_id, device_id=device_id, **values))
        session.add_all(rows)
        session.flush()
        self._db.audit(
            session,
            actor,
            "points.add",
            "job",
            job_id,
            {
                "device_id": device_id,
                "count": len(rows),
                "points": [row.point for row in rows],
                "points_sha256": sha256_hex(
                    [point_content(row) for row in sorted(rows, key=lambda row: row.point)]
                ),
            },
        )
        return rows

    def settle_from_samples(
        self,
        job_id: int,
        device_id: int,
        *,
        actor: str,
        skip_s: float = 0.0,
        commands: Mapping[int, tuple[float, float]] | None = None,
    ) -> list[SettledPoint]:
        """Average each grid point's raw samples after discarding the first skip_s seconds
        (settling)."""
        skip_s = require_number("skip_s", skip_s)
        if skip_s < 0:
            raise InputError(
                f"skip_s={skip_s} is negative; it is the settling time discarded at each point"
            )
        with self._db.session() as session:
            t = SampleRow.__table__
            rows = session.execute(
                sa.select(t.c.point, t.c.t_s, t.c.ch_x, t.c.ch_y, t.c.ch_z, t.c.temp_c)
                .where(t.c.job_id == job_id, t.c.device_id == device_id, t.c.point.is_not(None))
                .order_by(t.c.point, t.c.t_s)
            ).all()
        by_point: dict[int, list[Any]] = {}
        for row in rows:
            by_point.setdefault(row.point, []).append(row)
        points: list[SettledPointFields] = []
        for point, samples in sorted(by_point.items()):
            t0 = samples[0].t_s + skip_s
            settled = [sample for sample in samples if sample.t_s >= t0]
            if not settled:
                continue
            cmd = (commands or {}).get(point, (None, None))
            points.append(_point_from_samples(point, settled, cmd))
        if not points:
            raise InputError(
                f"job {job_id} has no raw samples of device {device_id} with a grid point"
            )
        return self.add_settled_points(job_id, device_id, points, actor=actor)

    def settled_points(
        self, job_id: int, device_id: int | None = None, from_point: int | None = None
    ) -> list[SettledPoint]:
        """A job's settled points (of one device; from a point index on: what a follower has not
        seen)."""
        with self._db.session() as session:
            stmt = sa.select(SettledPoint).where(SettledPoint.job_id == job_id)
            if device_id is not None:
                stmt = stmt.where(SettledPoint.device_id == device_id)
            if from_point is not None:
                stmt = stmt.where(SettledPoint.point >= from_point)
            return list(session.scalars(stmt.order_by(SettledPoint.device_id, SettledPoint.point)))

    def points_sha256_by_job(self, job_ids: Sequence[int]) -> dict[str, dict[str, str]]:
        """Per job, the SHA-256 of every device's settled points (keyed by job id, then device id,
        as text): what a record fitted on those jobs' points commits to, and `db verify` checks."""
        out: dict[str, dict[str, str]] = {}
        for job_id in job_ids:
            by_device: dict[int, list[SettledPoint]] = {}
            for settled_point in self.settled_points(job_id):
                by_device.setdefault(settled_point.device_id, []).append(settled_point)
            out[str(job_id)] = {
                str(device_id): points_sha256(pts) for device_id, pts in sorted(by_device.items())
            }
        return out


def _point_values(i: int, given: Mapping[str, object]) -> SettledPointFields:
    """The fields of the i-th settled point given, checked: known ones only, the required ones
    there, counts non-negative integers and every other value finite (checked in the order of
    POINT_FIELDS)."""
    unknown = set(given) - set(POINT_FIELDS)
    missing = [k for k in POINT_REQUIRED if given.get(k) is None]
    if unknown or missing:
        raise InputError(
            f"settled point [{i}]: unknown fields {sorted(unknown)}, missing {missing}"
        )

    def count(k: str) -> int:
        value = given[k]
        if not isinstance(value, int) or value < 0:
            raise InputError(f"settled point [{i}]: {k} must be a non-negative integer")
        return value

    def finite(k: str) -> float | None:
        return require_finite(f"settled point [{i}] {k}", given.get(k))

    return {
        "point": count("point"),
        "cmd_x_deg": finite("cmd_x_deg"),
        "cmd_y_deg": finite("cmd_y_deg"),
        "n_samples": count("n_samples"),
        "t_start_s": finite("t_start_s"),
        "t_end_s": finite("t_end_s"),
        "ch_x_mean": finite("ch_x_mean"),
        "ch_y_mean": finite("ch_y_mean"),
        "ch_z_mean": finite("ch_z_mean"),
        "ch_x_std": finite("ch_x_std"),
        "ch_y_std": finite("ch_y_std"),
        "ch_z_std": finite("ch_z_std"),
        "temp_c_mean": finite("temp_c_mean"),
    }


def _point_from_samples(
    point: int, samples: Sequence[Any], cmd: tuple[float | None, float | None]
) -> SettledPointFields:
    """A grid point's settled values from its samples after settling: their means and spreads."""
    channels = {
        name: [getattr(sample, name) for sample in samples]
        for name in ("ch_x", "ch_y", "ch_z", "temp_c")
    }
    return {
        "point": point,
        "cmd_x_deg": cmd[0],
        "cmd_y_deg": cmd[1],
        "n_samples": len(samples),
        "t_start_s": samples[0].t_s,
        "t_end_s": samples[-1].t_s,
        "ch_x_mean": mean_or_none(channels["ch_x"]),
        "ch_y_mean": mean_or_none(channels["ch_y"]),
        "ch_z_mean": mean_or_none(channels["ch_z"]),
        "ch_x_std": std_or_none(channels["ch_x"]),
        "ch_y_std": std_or_none(channels["ch_y"]),
        "ch_z_std": std_or_none(channels["ch_z"]),
        "temp_c_mean": mean_or_none(channels["temp_c"]),
    }


def point_samples_sha256(session: Session, job_id: int, device_id: int, point: int) -> str | None:
    """The SHA-256 of the raw samples stored for one point of one device of a job (None when it has
    none)."""
    t = SampleRow.__table__
    rows = session.execute(
        sa.select(*(t.c[name] for name in SAMPLE_FIELDS))
        .where(t.c.job_id == job_id, t.c.device_id == device_id, t.c.point == point)
        .order_by(t.c.t_s, t.c.id)
    ).all()
    return samples_sha256(rows) if rows else None


def mean_or_none(values: Sequence[float | None]) -> float | None:
    """The mean, or None when a value is missing (or there are none)."""
    known = [value for value in values if value is not None]
    if len(known) != len(values) or not known:
        return None
    return math.fsum(known) / len(known)


def std_or_none(values: Sequence[float | None]) -> float | None:
    """Sample standard deviation (n - 1), two-pass for precision."""
    known = [value for value in values if value is not None]
    if len(known) < 2 or len(known) != len(values):
        return None
    mean = math.fsum(known) / len(known)
    return math.sqrt(math.fsum((value - mean) ** 2 for value in known) / (len(known) - 1))
