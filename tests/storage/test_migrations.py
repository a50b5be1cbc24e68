"""Upgrade from empty, downgrade and upgrade again, models == migrations, the `tiltlab db`
commands."""

from __future__ import annotations

import pytest
import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext

from service import cli
from service.config import get_settings
from service.storage.engine import make_engine
from service.storage.migrate import current_revision, downgrade, head_revision, upgrade
from service.storage.models import APPEND_ONLY_TABLES, Base

TABLES = set(Base.metadata.tables)


def _tables(engine: sa.Engine) -> set[str]:
    return set(sa.inspect(engine).get_table_names()) - {"alembic_version"}


def _triggers(engine: sa.Engine) -> set[str]:
    with engine.connect() as conn:
        if engine.dialect.name == "sqlite":
            sql = "SELECT name FROM sqlite_master WHERE type = 'trigger'"
        else:
            sql = (
                "SELECT tgname FROM pg_trigger t JOIN pg_class c ON c.oid = t.tgrelid WHERE NOT "
                "tgisinternal AND c.relnamespace = current_schema()::regnamespace"
            )
        return {name for (name,) in conn.exec_driver_sql(sql)}


def test_upgrade_from_empty(empty_engine: sa.Engine) -> None:
    assert current_revision(empty_engine) is None
    assert _tables(empty_engine) == set()
    upgrade(empty_engine)
    assert current_revision(empty_engine) == head_revision()
    assert _tables(empty_engine) == TABLES
    triggers = _triggers(empty_engine)
    for table in (*APPEND_ONLY_TABLES, "samples"):
        assert any(table in name for name in triggers), f"no guard trigger on {table}"
    upgrade(empty_engine)  # idempotent
    assert current_revision(empty_engine) == head_revision()


def test_downgrade_to_base_and_upgrade_again(empty_engine: sa.Engine) -> None:
    engine = empty_engine
    upgrade(engine)
    downgrade(engine, "base")
    assert current_revision(engine) is None
    assert _tables(engine) == set()
    assert _triggers(engine) == set()
    upgrade(engine)
    assert current_revision(engine) == head_revision()
    assert _tables(engine) == TABLES


def test_models_and_migrations_describe_the_same_schema(empty_engine: sa.Engine) -> None:
    upgrade(empty_engine)
    with empty_engine.connect() as conn:
        ctx = MigrationContext.configure(
            conn, opts={"compare_type": True, "compare_server_default": True}
        )
        diff = compare_metadata(ctx, Base.metadata)
    assert diff == []


def test_sqlite_connections_use_wal_and_foreign_keys(tmp_path) -> None:  # type: ignore[no-untyped-def]
    engine = make_engine(f"sqlite:///{tmp_path / 'sub' / 'x.db'}")  # creates the directory too
    with engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
        assert conn.exec_driver_sql("PRAGMA busy_timeout").scalar() == 30_000
        assert conn.exec_driver_sql("PRAGMA synchronous").scalar() == 1  # NORMAL
    engine.dispose()


def test_postgresql_urls_get_psycopg3() -> None:
    assert make_engine("postgresql://u@h/db").dialect.driver == "psycopg"


def test_db_commands(db_url: str, tmp_path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.delenv("TILTLAB_CONFIG", raising=False)
    monkeypatch.setenv("TILTLAB_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("TILTLAB_DATABASE_URL", db_url)
    get_settings.cache_clear()
    try:
        assert cli.main(["db", "current"]) == 0
        assert "revision none" in capsys.readouterr().out
        assert cli.main(["db", "upgrade"]) == 0
        assert f"at revision {head_revision()}" in capsys.readouterr().out
        assert cli.main(["db", "verify"]) == 0
        assert "OK" in capsys.readouterr().out
        assert cli.main(["db", "downgrade", "base", "--yes"]) == 0
        assert cli.main(["db", "current"]) == 0
        assert "revision none" in capsys.readouterr().out
        assert cli.main(["db", "upgrade"]) == 0
    finally:
        get_settings.cache_clear()
