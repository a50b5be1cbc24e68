"""The test PostgreSQL server (TILTLAB_TEST_POSTGRES_URL, default
postgresql+psycopg://root@127.0.0.1:5432/test), and an engine on it to make and drop a test's
schema; a test skips, saying why, if no server answers."""

from __future__ import annotations

import os

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
