"""Engine factory: SQLite (embedded default) or PostgreSQL from a URL.

SQLite connections get WAL (readers never block the writer), foreign keys on (off by default
in SQLite), a busy timeout (wait for the lock instead of failing), synchronous=NORMAL (durable
at each WAL checkpoint, consistent after a crash). Transactions are begun explicitly so that DDL
is transactional too and writers can take the write lock up front (see `write_engine`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.engine import make_url

from service.errors import InputError

_BEGIN_OPTION = "tiltlab_sqlite_begin"
# libpq: give up connecting after 10 s; probe an idle connection after 10 s, every 5 s, 3 times;
# drop a connection whose sent data stays unacknowledged for 30 s.
_PG_CONNECT_TIMEOUTS = {
    "connect_timeout": 10,
    "keepalives": 1,
    "keepalives_idle": 10,
    "keepalives_interval": 5,
    "keepalives_count": 3,
    "tcp_user_timeout": 30_000,
}


def normalise_url(url: str) -> sa.URL:
    try:
        db_url = make_url(url)
    except sa.exc.ArgumentError as exc:
        raise InputError(f"database URL {url!r} is not a valid SQLAlchemy URL") from exc
    if db_url.drivername in ("postgresql", "postgres"):
        db_url = db_url.set(drivername="postgresql+psycopg")
    if db_url.get_backend_name() not in ("sqlite", "postgresql"):
        raise InputError(
            f"database URL {db_url.render_as_string()!r}: only sqlite and postgresql are supported"
        )
    return db_url


def make_engine(url: str | sa.URL, *, busy_timeout_ms: int = 30_000, **kwargs: Any) -> sa.Engine:
    db_url = normalise_url(url) if isinstance(url, str) else url
    if db_url.get_backend_name() == "sqlite":
        return _sqlite_engine(db_url, busy_timeout_ms, **kwargs)
    kwargs.setdefault("pool_pre_ping", True)
    # A server that vanishes without a word (a cable pulled, a host frozen) must fail a connection
    # in seconds, not hang it: the daemon then knows the database is away and waits it out
    # (outage.py).
    connect_args = {**_PG_CONNECT_TIMEOUTS, **kwargs.pop("connect_args", {})}
    return sa.create_engine(db_url, connect_args=connect_args, **kwargs)


def _sqlite_engine(u: sa.URL, busy_timeout_ms: int, **kwargs: Any) -> sa.Engine:
    database = u.database or ""
    in_memory = database in ("", ":memory:") or database.startswith("file::memory:")
    if not in_memory:
        folder = Path(database).expanduser().parent
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:  # a setting that cannot work: one line naming it, not a traceback
            raise InputError(
                f"TILTLAB_DATABASE_URL: the SQLite file {database} cannot be made, its folder "
                f"{folder} cannot be created ({exc.strerror}); set TILTLAB_DATABASE_URL (or "
                "TILTLAB_DATA_DIR) to a file in a folder this user can write"
            ) from None
    connect_args = kwargs.pop("connect_args", {})
    connect_args.setdefault("timeout", busy_timeout_ms / 1000)
    connect_args.setdefault("check_same_thread", False)
    engine = sa.create_engine(u, connect_args=connect_args, **kwargs)

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn: Any, _record: Any) -> None:
        dbapi_conn.isolation_level = None  # the driver must not open transactions behind our back
        cur = dbapi_conn.cursor()
        if not in_memory:
            cur.execute("PRAGMA journal_mode=WAL")
        cur.execute("PRAGMA foreign_keys=ON")
        cur.execute(f"PRAGMA busy_timeout={int(busy_timeout_ms)}")
        cur.execute("PRAGMA synchronous=NORMAL")
        cur.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn: sa.Connection) -> None:
        mode = conn.get_execution_options().get(_BEGIN_OPTION, "DEFERRED")
        conn.exec_driver_sql(f"BEGIN {mode}")

    return engine


def write_engine(engine: sa.Engine) -> sa.Engine:
    """The same engine, but on SQLite every transaction takes the write lock at BEGIN.

    A deferred SQLite transaction that reads first and writes later fails with "database is
    locked" if another writer committed in between; taking the lock up front makes it wait.
    """
    if engine.dialect.name == "sqlite":
        return engine.execution_options(**{_BEGIN_OPTION: "IMMEDIATE"})
    return engine


def redacted(url: str | sa.URL) -> str:
    db_url = make_url(url) if isinstance(url, str) else url
    return db_url.render_as_string(hide_password=True)
