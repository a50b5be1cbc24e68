"""Settled grid points of a job: added directly or averaged from the job's raw samples."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import sqlalchemy as sa

from service.errors import InputError
from service.storage.canonical import sha256_hex
from service.storage.errors import IllegalTransition
from service.storage.models import Sample as SampleRow
from service.storage.models import SettledPoint
from service.storage.store.base import StoreBase
from service.storage.store.checks import _finite
from service.storage.store.hashing import _POINT_FIELDS, _POINT_REQUIRED, point_content


class PointsStore(StoreBase):
    def add_settled_points(
        self, job_id: int, device_id: int, points: Sequence[Mapping[str, Any]], *, actor: str
    ) -> list[SettledPoint]:
        with self._tx() as s:
            job = self._job(s, job_id)
            self._device(s, device_id)
            if job.state != "running":
                raise IllegalTransition(f"job {job_id} is {job.state}; settled points are added while it runs")
            rows = []
            for i, p in enumerate(points):
                unknown = set(p) - set(_POINT_FIELDS)
                missing = [k for k in _POINT_REQUIRED if p.get(k) is None]
                if unknown or missing:
                    raise InputError(f"settled point [{i}]: unknown fields {sorted(unknown)}, missing {missing}")
                values: dict[str, Any] = {}
                for k in _POINT_FIELDS:
                    if k in ("point", "n_samples"):
                        if not isinstance(p[k], int) or p[k] < 0:
                            raise InputError(f"settled point [{i}]: {k} must be a non-negative integer")
                        values[k] = p[k]
                    else:
                        values[k] = _finite(f"settled point [{i}] {k}", p.get(k))
                rows.append(SettledPoint(job_id=job_id, device_id=device_id, **values))
            s.add_all(rows)
            s.flush()
            self._audit(
                s, actor, "points.add", "job", job_id,
                {"device_id": device_id, "count": len(rows), "points": [r.point for r in rows],
                 "points_sha256": sha256_hex([point_content(r) for r in sorted(rows, key=lambda r: r.point)])},
            )  # fmt: skip
            return rows

    def settle_from_samples(
        self, job_id: int, device_id: int, *, actor: str, skip_s: float = 0.0,
        commands: Mapping[int, tuple[float, float]] | None = None,
    ) -> list[SettledPoint]:  # fmt: skip
        """Average each grid point's raw samples after discarding the first skip_s seconds (settling)."""
        skip_s = _finite("skip_s", skip_s, optional=False)  # type: ignore[assignment]
        if skip_s < 0:
            raise InputError(f"skip_s={skip_s} is negative; it is the settling time discarded at each point")
        with self._read() as s:
            t = SampleRow.__table__
            rows = s.execute(
                sa.select(t.c.point, t.c.t_s, t.c.ch_x, t.c.ch_y, t.c.ch_z, t.c.temp_c)
                .where(t.c.job_id == job_id, t.c.device_id == device_id, t.c.point.is_not(None))
                .order_by(t.c.point, t.c.t_s)
            ).all()
        by_point: dict[int, list[Any]] = {}
        for r in rows:
            by_point.setdefault(r.point, []).append(r)
        points = []
        for point, rs in sorted(by_point.items()):
            t0 = rs[0].t_s + skip_s
            rs = [r for r in rs if r.t_s >= t0]
            if not rs:
                continue
            cmd = (commands or {}).get(point, (None, None))
            points.append({
                "point": point, "cmd_x_deg": cmd[0], "cmd_y_deg": cmd[1], "n_samples": len(rs),
                "t_start_s": rs[0].t_s, "t_end_s": rs[-1].t_s,
                "ch_x_mean": _mean([r.ch_x for r in rs]), "ch_y_mean": _mean([r.ch_y for r in rs]),
                "ch_z_mean": _mean([r.ch_z for r in rs]), "ch_x_std": _std([r.ch_x for r in rs]),
                "ch_y_std": _std([r.ch_y for r in rs]), "ch_z_std": _std([r.ch_z for r in rs]),
                "temp_c_mean": _mean([r.temp_c for r in rs]),
            })  # fmt: skip
        if not points:
            raise InputError(f"job {job_id} has no raw samples of device {device_id} with a grid point")
        return self.add_settled_points(job_id, device_id, points, actor=actor)

    def settled_points(self, job_id: int, device_id: int | None = None,
                       from_point: int | None = None) -> list[SettledPoint]:
        """A job's settled points (of one device; from a point index on: what a follower has not seen)."""
        with self._read() as s:
            stmt = sa.select(SettledPoint).where(SettledPoint.job_id == job_id)
            if device_id is not None:
                stmt = stmt.where(SettledPoint.device_id == device_id)
            if from_point is not None:
                stmt = stmt.where(SettledPoint.point >= from_point)
            return list(s.scalars(stmt.order_by(SettledPoint.device_id, SettledPoint.point)))


def _mean(values: Sequence[float | None]) -> float | None:
    if any(v is None for v in values) or not values:
        return None
    return math.fsum(values) / len(values)  # type: ignore[arg-type]


def _std(values: Sequence[float | None]) -> float | None:
    """Sample standard deviation (n - 1), two-pass for precision."""
    if len(values) < 2 or any(v is None for v in values):
        return None
    m = math.fsum(values) / len(values)  # type: ignore[arg-type]
    return math.sqrt(math.fsum((v - m) ** 2 for v in values) / (len(values) - 1))  # type: ignore[operator]
