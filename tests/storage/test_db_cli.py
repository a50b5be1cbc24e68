"""`tiltlab db`: a downgrade takes an explicit revision and --yes and backs SQLite up first;
`db backup`; commands that only read never create a database."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest
import sqlalchemy as sa

from service import cli
from service.config import get_settings
from service.storage.engine import make_engine
from service.storage.migrate import current_revision, head_revision
from service.storage.store import Store


@pytest.fixture
def configured(db_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):  # type: ignore[no-untyped-def]
    monkeypatch.delenv("TILTLAB_CONFIG", raising=False)
    monkeypatch.setenv("TILTLAB_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("TILTLAB_DATABASE_URL", db_url)
    get_settings.cache_clear()
    yield db_url
    get_settings.cache_clear()


def _upgraded_with_a_device(url: str) -> None:
    assert cli.main(["db", "upgrade"]) == 0
    engine = make_engine(url)
    Store(engine).devices.add_device("NS-25/E2", "SN1001", "dut", actor="alice")
    engine.dispose()


def _revision(url: str) -> str | None:
    engine = make_engine(url)
    try:
        return current_revision(engine)
    finally:
        engine.dispose()


def _main_exit(argv: list[str]) -> int:
    try:
        return cli.main(argv)
    except SystemExit as exc:  # argparse refusals
        return int(exc.code or 0)


def test_downgrade_needs_a_named_revision(configured: str, capsys) -> None:  # type: ignore[no-untyped-def]
    _upgraded_with_a_device(configured)
    capsys.readouterr()
    assert _main_exit(["db", "downgrade"]) == 2
    assert "revision" in capsys.readouterr().err
    assert _revision(configured) == head_revision()


def test_downgrade_without_yes_changes_nothing(configured: str, capsys) -> None:  # type: ignore[no-untyped-def]
    _upgraded_with_a_device(configured)
    capsys.readouterr()
    assert cli.main(["db", "downgrade", "base"]) == 2
    err = capsys.readouterr().err
    assert "--yes" in err and "calibration records" in err and len(err.strip().splitlines()) == 1
    assert _revision(configured) == head_revision()


def test_downgrade_to_an_unknown_revision_is_refused(configured: str, capsys) -> None:  # type: ignore[no-untyped-def]
    _upgraded_with_a_device(configured)
    capsys.readouterr()
    assert cli.main(["db", "downgrade", "nosuch", "--yes"]) == 2
    err = capsys.readouterr().err
    assert "no revision 'nosuch'" in err and "base" in err
    assert _revision(configured) == head_revision()


def test_downgrade_backs_sqlite_up_first_and_is_clean_at_base(  # type: ignore[no-untyped-def]
    configured: str, backend: str, capsys
) -> None:
    _upgraded_with_a_device(configured)
    capsys.readouterr()
    assert cli.main(["db", "downgrade", "base", "--yes"]) == 0
    out = capsys.readouterr()
    assert _revision(configured) is None
    if backend == "sqlite":
        line = next(x for x in out.out.splitlines() if x.startswith("backed up "))
        backup = Path(line.rsplit(" to ", 1)[1])
        assert backup.is_file()
        with sqlite3.connect(backup) as conn:
            assert (
                conn.execute("SELECT version_num FROM alembic_version").fetchone()[0]
                == head_revision()
            )
            assert conn.execute("SELECT serial FROM devices").fetchall() == [("SN1001",)]
    # at base already: a message, not a traceback
    assert cli.main(["db", "downgrade", "base", "--yes"]) == 0
    assert "already at base" in capsys.readouterr().err
    assert cli.main(["db", "downgrade", head_revision(), "--yes"]) == 2
    assert "already at base" in capsys.readouterr().err


def test_backup_of_sqlite_is_a_consistent_copy(
    configured: str,
    backend: str,
    tmp_path: Path,  # type: ignore[no-untyped-def]
    capsys,
) -> None:
    if backend != "sqlite":
        pytest.skip("SQLite only")
    _upgraded_with_a_device(configured)
    capsys.readouterr()
    out = tmp_path / "copy.db"
    assert cli.main(["db", "backup", "--out", str(out)]) == 0
    assert f"to {out}" in capsys.readouterr().out
    with sqlite3.connect(out) as conn:
        assert conn.execute("SELECT serial FROM devices").fetchall() == [("SN1001",)]
    assert not list(tmp_path.glob(".copy.db.*"))  # no partial file left
    # never over an existing file
    assert cli.main(["db", "backup", "--out", str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert cli.main(["db", "backup", "--out", str(tmp_path / "nosuch" / "x.db")]) == 2


def test_backup_of_postgresql_prints_pg_dump(configured: str, backend: str, capsys) -> None:  # type: ignore[no-untyped-def]
    if backend != "postgresql":
        pytest.skip("PostgreSQL only")
    _upgraded_with_a_device(configured)
    capsys.readouterr()
    assert cli.main(["db", "backup", "--out", "lab.dump"]) == 0
    out = capsys.readouterr().out.strip()
    assert out.startswith("pg_dump --format=custom --file=lab.dump")
    assert "--schema=tiltlab_test_" in out
    assert cli.main(["db", "downgrade", "base"]) == 2
    assert "pg_dump" in capsys.readouterr().err


def test_read_only_commands_create_no_database(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,  # type: ignore[no-untyped-def]
    capsys,
) -> None:
    data = tmp_path / "data"
    monkeypatch.delenv("TILTLAB_CONFIG", raising=False)
    monkeypatch.delenv("TILTLAB_DATABASE_URL", raising=False)
    monkeypatch.setenv("TILTLAB_DATA_DIR", str(data))
    get_settings.cache_clear()
    try:
        assert cli.main(["db", "current"]) == 0
        assert "revision none" in capsys.readouterr().out
        assert cli.main(["db", "verify"]) == 1
        assert cli.main(["db", "history"]) == 0
        assert head_revision() in capsys.readouterr().out
        assert cli.main(["db", "downgrade", "base", "--yes"]) == 2
        assert cli.main(["db", "backup", "--out", str(tmp_path / "b.db")]) == 2
        assert not data.exists()
        assert not (tmp_path / "b.db").exists()
    finally:
        get_settings.cache_clear()


def test_sqlite_url_helpers_refuse_memory() -> None:
    from service.errors import InputError
    from service.storage.backup import sqlite_path

    with pytest.raises(InputError):
        sqlite_path("sqlite://")
    assert sqlite_path(sa.make_url("postgresql+psycopg://u@h/db")) is None
