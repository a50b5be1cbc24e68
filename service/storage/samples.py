"""Raw samples: the fast bulk path, the reads the service needs, and retention.

Samples are plain tuples (`Sample`) and go to the database with the driver's own bulk path
on SQLAlchemy's connection (executemany for SQLite, COPY for PostgreSQL): building ORM
objects for millions of readings would cost more than the database does.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from itertools import chain
from operator import itemgetter
from typing import Any, NamedTuple, cast

import sqlalchemy as sa

from service.errors import InputError
from service.storage.models import SAMPLE_SOURCES
from service.storage.models import Sample as SampleRow

COLUMNS = ("device_id", "t_s", "ch_x", "ch_y", "ch_z", "temp_c", "job_id", "point", "source")


class Sample(NamedTuple):
    device_id: int
    t_s: float  # seconds since the Unix epoch, UTC
    ch_x: float
    ch_y: float
    ch_z: float | None = None
    temp_c: float | None = None
    job_id: int | None = None
    point: int | None = None
    source: str = "monitoring"  # or "calibration" (then job_id is required)


def _finite_number(value: object) -> bool:
    return not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)


def check_sample(s: Sample) -> None:
    """Cheap checks at the producer, so a bad reading is refused where it is made, not in a batch
    later.

    Every number must be a finite int or float: SQLite would keep text in a REAL column, turn NaN
    into NULL and refuse it in a required column, where PostgreSQL stores NaN.
    """
    if len(s) != len(COLUMNS):
        raise InputError(f"sample has {len(s)} fields, expected {len(COLUMNS)}: {COLUMNS}")
    # plain tuples in COLUMNS order are fine too
    device_id, t_s, ch_x, ch_y, ch_z, temp_c, job_id, _, source = s
    if source not in SAMPLE_SOURCES:
        raise InputError(f"sample source {source!r} is not one of {SAMPLE_SOURCES}")
    if source == "calibration" and job_id is None:
        raise InputError("a calibration sample needs its job_id")
    if not _finite_number(t_s):
        raise InputError(f"sample t_s={t_s!r} is not a finite time in seconds")
    if isinstance(device_id, bool) or not isinstance(device_id, int):
        raise InputError(f"sample device_id={device_id!r} is not an integer id")
    _check_readings(t_s, ch_x, ch_y, ch_z, temp_c)


def _check_readings(t_s: object, ch_x: object, ch_y: object, ch_z: object, temp_c: object) -> None:
    """check_sample's last step: the channels (required) and temperature (optional) are finite."""
    for name, value, optional in (
        ("ch_x", ch_x, False),
        ("ch_y", ch_y, False),
        ("ch_z", ch_z, True),
        ("temp_c", temp_c, True),
    ):
        if not (optional and value is None) and not _finite_number(value):
            raise InputError(f"sample {name}={value!r} at t_s={t_s!r} is not a finite number")


def _numbers_look_fine(rows: Sequence[Sample]) -> bool:
    """check_samples' pass over the shape and numbers of a batch (raises on text or None)."""
    return (
        set(map(len, rows)) <= {len(COLUMNS)}
        # a str or None raises, a float spoils the type
        and type(sum(map(itemgetter(0), rows))) is int
        # A NaN or inf anywhere spoils the sum, text raises; the optional columns drop None (and
        # zeros).
        and math.isfinite(
            sum(chain(map(itemgetter(1), rows), map(itemgetter(2), rows), map(itemgetter(3), rows)))
        )
        and math.isfinite(
            sum(
                chain(
                    filter(None, map(itemgetter(4), rows)),
                    filter(None, map(itemgetter(5), rows)),
                )
            )
        )
        and set(map(type, map(itemgetter(1), rows))) <= {float, int}  # not bool
    )


def _sources_look_fine(rows: Sequence[Sample]) -> bool:
    """check_samples' pass over the sources: known ones, and a job for every calibration sample."""
    return set(map(itemgetter(8), rows)) <= set(SAMPLE_SOURCES) and not any(
        sample[6] is None for sample in rows if sample[8] == "calibration"
    )


def check_samples(rows: Sequence[Sample]) -> None:
    """check_sample for a whole batch, in C-speed passes; the slow path only to name the culprit."""
    try:
        ok = _numbers_look_fine(rows) and _sources_look_fine(rows)
    except (TypeError, ValueError, OverflowError, IndexError):
        ok = False
    if not ok:
        for sample in rows:
            check_sample(sample)


_ROWS_PER_STATEMENT = 100  # 900 parameters: below SQLite's limit even in old builds (999)
_VALUES = "(" + ", ".join("?" * len(COLUMNS)) + ")"
_INSERT_ONE = f"INSERT INTO samples ({', '.join(COLUMNS)}) VALUES {_VALUES}"
_INSERT_MANY = f"INSERT INTO samples ({', '.join(COLUMNS)}) VALUES " + ", ".join(
    [_VALUES] * _ROWS_PER_STATEMENT
)
_INSERT_FORMAT = (
    f"INSERT INTO samples ({', '.join(COLUMNS)}) VALUES ({', '.join(['%s'] * len(COLUMNS))})"
)
_COPY_SQL = f"COPY samples ({', '.join(COLUMNS)}) FROM STDIN"


def insert_samples(conn: sa.Connection, rows: Sequence[Sequence[object]]) -> int:
    """Insert in the caller's transaction with the driver's bulk path; returns the count."""
    if not rows:
        return 0
    if conn.dialect.name == "postgresql":
        dbapi_conn = conn.connection.driver_connection
        dbapi = conn.dialect.loaded_dbapi
        try:
            with dbapi_conn.cursor() as cur, cur.copy(_COPY_SQL) as copy:  # type: ignore[union-attr]
                for row in rows:
                    copy.write_row(row)
        except dbapi.Error as exc:  # same exception types as every other statement
            raise sa.exc.DBAPIError.instance(_COPY_SQL, None, exc, dbapi.Error) from exc
        return len(rows)
    if conn.dialect.name != "sqlite":
        conn.exec_driver_sql(_INSERT_FORMAT, list(rows))
        return len(rows)
    # Multi-row INSERTs through executemany: one statement step (and one release of the GIL)
    # per 100 rows instead of per row, which is what lets the writer thread keep its pace
    # while acquisition threads run.
    full = len(rows) - len(rows) % _ROWS_PER_STATEMENT
    if full:
        flat = list(chain.from_iterable(rows[:full]))
        step = _ROWS_PER_STATEMENT * len(COLUMNS)
        conn.exec_driver_sql(
            _INSERT_MANY, [tuple(flat[i : i + step]) for i in range(0, len(flat), step)]
        )
    if full < len(rows):
        conn.exec_driver_sql(_INSERT_ONE, list(rows[full:]))
    return len(rows)


def samples_stored(conn: sa.Connection, rows: Sequence[Sample]) -> bool:
    """Whether a batch written in one transaction is already in the database: its first and last
    samples are (a batch commits whole or not at all). What makes a repeated write safe after a
    COMMIT whose answer was lost; two index probes on (device_id, t_s)."""
    if not rows:
        return True
    for row in (rows[0], rows[-1]):
        sample = Sample._make(row)
        found = conn.execute(
            sa.select(_t.c.id)
            .where(
                _t.c.device_id == sample.device_id,
                _t.c.t_s == sample.t_s,
                _t.c.source == sample.source,
                _t.c.job_id.is_not_distinct_from(sample.job_id),
                _t.c.point.is_not_distinct_from(sample.point),
            )
            .limit(1)
        ).first()
        if found is None:
            return False
    return True


def insert_samples_once(conn: sa.Connection, rows: Sequence[Sample]) -> int:
    """`insert_samples`, unless this very batch is already stored (a repeat after a lost COMMIT
    answer): the check and the insert in the caller's one transaction. Returns the count
    inserted."""
    if samples_stored(conn, rows):
        return 0
    return insert_samples(conn, rows)


def write_samples(engine: sa.Engine, rows: Iterable[Sample], *, batch_size: int = 5000) -> int:
    """Synchronous convenience: check and insert, one transaction per batch."""
    from service.storage.engine import write_engine

    total, batch = 0, []
    weng = write_engine(engine)
    for sample in rows:
        batch.append(sample)
        if len(batch) >= batch_size:
            check_samples(batch)
            with weng.begin() as conn:
                total += insert_samples(conn, batch)
            batch = []
    if batch:
        check_samples(batch)
        with weng.begin() as conn:
            total += insert_samples(conn, batch)
    return total


_t = cast(sa.Table, SampleRow.__table__)
_SELECT_COLS = [_t.c[name] for name in COLUMNS]


_LATEST_SQL = (
    f"SELECT {', '.join(COLUMNS)} FROM samples WHERE device_id = {{p}} ORDER BY t_s "
    "DESC LIMIT {p}"
)
_LATEST = {"qmark": _LATEST_SQL.format(p="?"), "format": _LATEST_SQL.format(p="%s")}


def latest_samples(conn: sa.Connection, device_id: int, n: int = 1000) -> list[Sample]:
    """The newest n samples of a device, newest first (one walk down the (device_id, t_s) index).

    Runs on the driver's cursor of SQLAlchemy's connection: wrapping 1,000 result rows costs
    about as much as the query itself.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise InputError(f"latest_samples: n={n!r} is not a count of samples (an integer >= 0)")
    sql = _LATEST.get(conn.dialect.paramstyle) or _LATEST["format"]
    dbapi = conn.dialect.loaded_dbapi
    cursor = conn.connection.dbapi_connection.cursor()  # type: ignore[union-attr]
    try:
        cursor.execute(sql, (int(device_id), int(n)))
        return list(map(Sample._make, cursor.fetchall()))
    except dbapi.Error as exc:
        raise sa.exc.DBAPIError.instance(sql, None, exc, dbapi.Error) from exc
    finally:
        cursor.close()


def samples_between(conn: sa.Connection, device_id: int, t0_s: float, t1_s: float) -> list[Sample]:
    stmt = (
        sa.select(*_SELECT_COLS)
        .where(_t.c.device_id == device_id, _t.c.t_s >= t0_s, _t.c.t_s < t1_s)
        .order_by(_t.c.t_s)
    )
    return [Sample(*row) for row in conn.execute(stmt)]


def job_samples(conn: sa.Connection, job_id: int, point: int | None = None) -> list[Sample]:
    stmt = sa.select(*_SELECT_COLS).where(_t.c.job_id == job_id)
    if point is not None:
        stmt = stmt.where(_t.c.point == point)
    return [Sample(*row) for row in conn.execute(stmt.order_by(_t.c.point, _t.c.t_s, _t.c.id))]


def count_samples(conn: sa.Connection, **where: object) -> int:
    stmt = sa.select(sa.func.count()).select_from(_t)
    for key, value in where.items():
        stmt = stmt.where(_t.c[key] == value)
    return int(conn.execute(stmt).scalar_one())


@dataclass(frozen=True)
class RetentionResult:
    cutoff_s: float
    policy: str
    deleted: int
    kept_thinned: int


def _check_retention(
    older_than: dt.timedelta, policy: str, thin_interval_s: float, now: dt.datetime | None
) -> None:
    """apply_retention's arguments checked before anything is deleted."""
    if policy not in ("thin", "drop"):
        raise InputError(f"retention policy {policy!r} is not 'thin' or 'drop'")
    if not isinstance(older_than, dt.timedelta):
        raise InputError(f"retention age {older_than!r} must be a datetime.timedelta")
    if older_than <= dt.timedelta(0):
        raise InputError("retention age must be positive")
    if now is not None and now.tzinfo is None:
        raise InputError(f"retention time now={now.isoformat()} has no timezone; give it in UTC")
    if policy == "thin" and not (thin_interval_s > 0):
        raise InputError("thin interval must be positive")


def _thin(
    conn: sa.Connection, scope: sa.ColumnElement[bool], thin_interval_s: float
) -> tuple[int, int]:
    """One device's old samples thinned to the first of each interval: (deleted, kept)."""
    bucket: sa.ColumnElement[Any]
    if conn.dialect.name == "postgresql":
        bucket = sa.func.floor(_t.c.t_s / thin_interval_s)
    else:
        bucket = sa.cast(_t.c.t_s / thin_interval_s, sa.Integer)  # t_s > 0: truncation is floor
    keep = sa.select(sa.func.min(_t.c.id)).where(scope).group_by(bucket)
    deleted = conn.execute(sa.delete(_t).where(scope, _t.c.id.not_in(keep))).rowcount
    kept = int(conn.execute(sa.select(sa.func.count()).select_from(_t).where(scope)).scalar_one())
    return deleted, kept


def apply_retention(
    conn: sa.Connection,
    *,
    older_than: dt.timedelta,
    policy: str = "thin",
    thin_interval_s: float = 60.0,
    now: dt.datetime | None = None,
) -> RetentionResult:
    """Drop, or thin to one sample per device per interval, the monitoring samples older than the
    age.

    Only rows with source='monitoring' are touched; the database triggers refuse the deletion of
    any other sample, so a mistake here cannot reach calibration data.
    """
    _check_retention(older_than, policy, thin_interval_s, now)
    now = now or dt.datetime.now(dt.UTC)
    cutoff_s = (now - older_than).timestamp()
    old = sa.and_(_t.c.source == "monitoring", _t.c.t_s < cutoff_s)
    kept = 0
    devices = [
        device for (device,) in conn.execute(sa.select(_t.c.device_id).where(old).distinct())
    ]
    deleted = 0
    for device_id in devices:  # one device at a time: each delete walks the (device_id, t_s) index
        scope = sa.and_(_t.c.device_id == device_id, old)
        if policy == "drop":
            deleted += conn.execute(sa.delete(_t).where(scope)).rowcount
            continue
        thinned_away, thinned_kept = _thin(conn, scope, thin_interval_s)
        deleted += thinned_away
        kept += thinned_kept
    return RetentionResult(cutoff_s=cutoff_s, policy=policy, deleted=deleted, kept_thinned=kept)
