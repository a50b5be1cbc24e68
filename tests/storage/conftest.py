"""Storage fixtures: every test that takes `db_url`, `engine` or `store` runs on SQLite and on PostgreSQL.

SQLite: a fresh file per test in tmp_path. PostgreSQL: a fresh schema per test in the database
at TILTLAB_TEST_POSTGRES_URL (default postgresql+psycopg://root@127.0.0.1:5432/test), selected
through the connection's search_path and dropped afterwards; skipped only if no server answers.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator

import pytest
import sqlalchemy as sa

from service.storage.engine import make_engine, redacted
from service.storage.migrate import upgrade
from service.storage.store import Store

PG_URL = os.environ.get("TILTLAB_TEST_POSTGRES_URL", "postgresql+psycopg://root@127.0.0.1:5432/test")

_pg_state: dict[str, object] = {}


def _pg_admin() -> sa.Engine:
    if "engine" not in _pg_state:
        engine = make_engine(PG_URL, poolclass=sa.pool.NullPool, connect_args={"connect_timeout": 3})
        try:
            with engine.connect() as conn:
                conn.execute(sa.text("SELECT 1"))
        except Exception as exc:  # noqa: BLE001 - any failure to connect means "no server here"
            _pg_state["error"] = f"PostgreSQL does not answer at {redacted(PG_URL)}: {type(exc).__name__}: {exc}"
        _pg_state["engine"] = engine
    if "error" in _pg_state:
        pytest.skip(str(_pg_state["error"]))
    return _pg_state["engine"]  # type: ignore[return-value]


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def backend(request: pytest.FixtureRequest) -> str:
    return request.param


@pytest.fixture
def db_url(backend: str, tmp_path) -> Iterator[str]:  # type: ignore[no-untyped-def]
    """The URL of a fresh, empty database (no schema yet)."""
    if backend == "sqlite":
        yield f"sqlite:///{tmp_path / 'tiltlab.db'}"
        return
    admin = _pg_admin()
    schema = f"tiltlab_test_{uuid.uuid4().hex[:12]}"
    with admin.begin() as conn:
        conn.execute(sa.text(f'CREATE SCHEMA "{schema}"'))
    url = sa.make_url(PG_URL).update_query_dict({"options": f"-csearch_path={schema}"})
    try:
        yield url.render_as_string(hide_password=False)
    finally:
        with admin.begin() as conn:
            conn.execute(sa.text(f'DROP SCHEMA "{schema}" CASCADE'))


@pytest.fixture
def empty_engine(db_url: str) -> Iterator[sa.Engine]:
    engine = make_engine(db_url)
    yield engine
    engine.dispose()


@pytest.fixture
def engine(empty_engine: sa.Engine) -> sa.Engine:
    upgrade(empty_engine)
    return empty_engine


@pytest.fixture
def store(engine: sa.Engine) -> Store:
    return Store(engine)


@pytest.fixture
def device(store: Store):  # type: ignore[no-untyped-def]
    return store.add_device("NS-25/E2", "SN1001", "dut", actor="alice", port="/dev/ttyUSB0",
                            port_settings={"baud": 115200, "parity": "N"})  # fmt: skip
