"""The test PostgreSQL server (TILTLAB_TEST_POSTGRES_URL, default
postgresql+psycopg://root@127.0.0.1:5432/test), and an engine on it to make and drop a test's
schema; a test skips, saying why, if no server answers."""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterator

import pytest
import sqlalchemy as sa

from service.storage.engine import make_engine, redacted

PG_URL = os.environ.get(
    "TILTLAB_TEST_POSTGRES_URL", "postgresql+psycopg://root@127.0.0.1:5432/test"
)

_pg_state: dict[str, object] = {}


def pg_admin() -> sa.Engine:
    """An engine on the server (made once); skips the test if the server does not answer."""
    if "engine" not in _pg_state:
        engine = make_engine(
            PG_URL, connect_args={"connect_timeout": 3, "options": "-csynchronous_commit=off"}
        )
        try:
            with engine.connect() as conn:
                conn.execute(sa.text("SELECT 1"))
        except Exception as exc:  # noqa: BLE001 - any failure to connect means "no server here"
            _pg_state["error"] = (
                f"PostgreSQL does not answer at {redacted(PG_URL)}: {type(exc).__name__}: {exc}"
            )
        _pg_state["engine"] = engine
    if "error" in _pg_state:
        pytest.skip(str(_pg_state["error"]))
    return _pg_state["engine"]  # type: ignore[return-value]


@contextlib.contextmanager
def fresh_schema_url(prefix: str = "tiltlab_test", options: str = "") -> Iterator[str]:
    """The URL of a fresh, empty schema in the test database (search_path on it, plus `options`),
    dropped afterwards; skips the test if no server answers.

    The schema's connections carry its name as application_name, so the drop can end them first (a
    killed writer's backend may still hold locks that DROP SCHEMA would wait on for ever)."""
    admin = pg_admin()
    schema = f"{prefix}_{uuid.uuid4().hex[:12]}"
    with admin.begin() as conn:
        conn.execute(sa.text(f'CREATE SCHEMA "{schema}"'))
    url = sa.make_url(PG_URL).update_query_dict(
        {"options": f"-csearch_path={schema} {options}".strip(), "application_name": schema}
    )
    try:
        yield url.render_as_string(hide_password=False)
    finally:
        with admin.begin() as conn:
            conn.execute(
                sa.text(
                    "SELECT pg_terminate_backend(pid) FROM pg_stat_activity"
                    " WHERE application_name = :schema"
                ),
                {"schema": schema},
            )
            conn.execute(sa.text("SET lock_timeout = '20s'"))
            conn.execute(sa.text(f'DROP SCHEMA "{schema}" CASCADE'))
