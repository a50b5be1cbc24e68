"""The database fixtures of the storage tests, shared with every test that needs a database (the
LIMS and the list queries): a test that takes `db_url` or `engine` runs on SQLite and on PostgreSQL.

SQLite: a fresh file per test in tmp_path. PostgreSQL: a fresh schema per test in the database
at TILTLAB_TEST_POSTGRES_URL (default postgresql+psycopg://root@127.0.0.1:5432/test), selected
through the connection's search_path and dropped afterwards; skipped only if no server answers.
"""

from __future__ import annotations

import io
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
import sqlalchemy as sa
from alembic import command

from service.storage.engine import make_engine
from service.storage.migrate import alembic_config, upgrade
from tests.helpers.postgres import fresh_schema_url


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """`-n auto`: half as many workers again as the cores this process may use. Most of a daemon
    test's time is simulated bench time the test waits out (a 2-core run kept its cores 62-68 % busy
    with one worker a core); PYTEST_XDIST_AUTO_NUM_WORKERS overrides it."""
    return max(1, len(os.sched_getaffinity(0)) * 3 // 2)


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def backend(request: pytest.FixtureRequest) -> str:
    return request.param


@pytest.fixture
def db_url(backend: str, tmp_path) -> Iterator[str]:  # type: ignore[no-untyped-def]
    """The URL of a fresh, empty database (no schema yet)."""
    if backend == "sqlite":
        yield f"sqlite:///{tmp_path / 'tiltlab.db'}"
        return
    # synchronous_commit=off: tests need no durability, and DDL-heavy commits wait less
    with fresh_schema_url("tiltlab_test", "-csynchronous_commit=off") as url:
        yield url


@pytest.fixture
def empty_engine(db_url: str) -> Iterator[sa.Engine]:
    engine = make_engine(db_url)
    yield engine
    engine.dispose()


@pytest.fixture(scope="session")
def sqlite_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A database migrated to head once per session; each test gets a copy of the file."""
    path = tmp_path_factory.mktemp("template") / "tiltlab.db"
    engine = make_engine(f"sqlite:///{path}")
    upgrade(engine)
    with engine.connect() as conn:
        conn.exec_driver_sql("PRAGMA wal_checkpoint(TRUNCATE)")
    engine.dispose()
    return path


@pytest.fixture(scope="session")
def postgres_schema_sql() -> str:
    """The migrations to head rendered as one SQL script (Alembic offline mode), run per test
    schema."""
    buffer = io.StringIO()
    cfg = alembic_config()
    cfg.output_buffer = buffer
    cfg.set_main_option("sqlalchemy.url", "postgresql+psycopg://")
    command.upgrade(cfg, "head", sql=True)
    return buffer.getvalue()


@pytest.fixture
def engine(db_url: str, backend: str, request: pytest.FixtureRequest) -> Iterator[sa.Engine]:
    """A database at the head revision. The real `upgrade` is exercised by test_migrations.py;
    here the same migrations are applied from a session-wide copy to keep the suite fast."""
    if backend == "sqlite":
        shutil.copyfile(request.getfixturevalue("sqlite_template"), sa.make_url(db_url).database)
        engine = make_engine(db_url)
    else:
        script = request.getfixturevalue("postgres_schema_sql")
        engine = make_engine(db_url)
        with engine.connect() as conn:
            # several statements: simple query protocol
            conn.connection.driver_connection.execute(script)
            conn.commit()
    yield engine
    engine.dispose()
