"""Schema migrations, configured in code so they work from any directory and any install.

The Alembic environment lives in the repository's `migrations/`; a wheel ships it as the
package `service.migrations` (see setup.py). Each upgrade or downgrade runs in one
transaction, on SQLite too, so a failed step leaves the schema as it was.
"""

from __future__ import annotations

from pathlib import Path

import sqlalchemy as sa
from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory

from service.resources import shipped_dir
from service.storage.engine import make_engine, write_engine

_PG_MIGRATION_LOCK = 0x7417_1AB0  # serialises concurrent start-ups on one PostgreSQL database


def _is_ours(path: Path) -> bool:
    env = path / "env.py"
    return env.is_file() and "service.storage" in env.read_text(encoding="utf-8")


def migrations_dir() -> Path:
    return shipped_dir("service.migrations", "migrations", _is_ours)


def alembic_config(connection: sa.Connection | None = None) -> Config:
    cfg = Config()
    cfg.set_main_option("script_location", str(migrations_dir()))
    cfg.set_main_option("path_separator", "os")
    cfg.attributes["connection"] = connection
    return cfg


def head_revision() -> str:
    head = ScriptDirectory.from_config(alembic_config()).get_current_head()
    assert head is not None
    return head


def current_revision(engine: sa.Engine) -> str | None:
    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def _run(engine: sa.Engine, fn, revision: str) -> None:  # type: ignore[no-untyped-def]
    with write_engine(engine).begin() as conn:
        if conn.dialect.name == "postgresql":
            conn.execute(sa.text("SELECT pg_advisory_xact_lock(:k)"), {"k": _PG_MIGRATION_LOCK})
        fn(alembic_config(conn), revision)


def upgrade(engine: sa.Engine, revision: str = "head") -> None:
    _run(engine, command.upgrade, revision)


def downgrade(engine: sa.Engine, revision: str = "-1") -> None:
    _run(engine, command.downgrade, revision)


def bootstrap(settings=None) -> sa.Engine:  # type: ignore[no-untyped-def]
    """What the service does at start-up: data directory, engine, schema at head."""
    from service.config import get_settings

    settings = settings or get_settings()
    Path(settings.data_dir).mkdir(parents=True, exist_ok=True)
    engine = make_engine(settings.database_url, busy_timeout_ms=settings.sqlite_busy_timeout_ms)
    upgrade(engine)
    return engine
