"""`tiltlab db upgrade|current|history|downgrade REVISION --yes|backup --out FILE|verify`.

Commands that only read (`current`, `history`, `verify`) never create a database. A downgrade
drops the tables of the migrations it undoes, so it takes an explicit revision and `--yes`,
and a SQLite database is backed up first (online backup API), the backup's path printed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from service.commands._args import add_command, add_subcommands
from service.errors import InputError

# storage and migrations are imported by the commands that use them, not by --help
if TYPE_CHECKING:
    from alembic.script import ScriptDirectory
    from sqlalchemy.engine import Engine

    from service.config import Settings


def run(args: argparse.Namespace) -> int:
    from service.config import get_settings
    from service.storage.backup import database_exists, sqlite_path
    from service.storage.engine import make_engine, redacted
    from service.storage.migrate import current_revision

    settings = get_settings()
    command = args.db_command
    if command == "upgrade":
        from service.storage.migrate import bootstrap

        engine = bootstrap(settings)
        print(f"{redacted(settings.database_url)}: at revision {current_revision(engine)} (head)")
        engine.dispose()
        return 0
    if command == "history":
        return _history()
    if command == "backup":
        return _backup(settings, args.out)
    where = redacted(settings.database_url)
    if not database_exists(settings.database_url):
        return _without_database(command, where, sqlite_path(settings.database_url))
    engine = make_engine(settings.database_url, busy_timeout_ms=settings.sqlite_busy_timeout_ms)
    try:
        if command == "current":
            return _current(engine, where)
        if command == "downgrade":
            return _downgrade(settings, engine, args.revision, args.yes)
        if command == "verify":
            return _verify(engine, where)
        raise ValueError(f"unknown db command {command!r}")
    finally:
        engine.dispose()


def _current(engine: Engine, where: str) -> int:
    """`current` on an existing database: its revision, and where it stands against the head."""
    from service.storage.migrate import current_revision, head_revision

    rev = current_revision(engine)
    head = head_revision()
    state = (
        "empty, run `tiltlab db upgrade`"
        if rev is None
        else ("head" if rev == head else f"head is {head}")
    )
    print(f"{where}: revision {rev or 'none'} ({state})")
    return 0


def _without_database(command: str, where: str, path: Path | None) -> int:
    """`current`, `verify` and `downgrade` when there is no database file: say so, create none."""
    if command == "current":
        print(
            f"{where}: revision none (no database file at {path} yet; `tiltlab db upgrade` "
            "creates it)"
        )
        return 0
    if command == "verify":
        print(f"{where}: no database file at {path} (run `tiltlab db upgrade`)", file=sys.stderr)
        return 1
    raise InputError(f"{where}: no database file at {path}; nothing to downgrade")


def _verify(engine: Engine, where: str) -> int:
    """`verify` on an existing database: every line of the report; exit 1 if anything is off."""
    from service.storage.migrate import current_revision
    from service.storage.verify import verify

    if current_revision(engine) is None:
        print(f"{where}: no schema yet (run `tiltlab db upgrade`)", file=sys.stderr)
        return 1
    report = verify(engine)
    for line in report.lines():
        print(line)
    return 0 if report.ok else 1


def _scripts() -> ScriptDirectory:
    from alembic.script import ScriptDirectory

    from service.storage.migrate import alembic_config

    return ScriptDirectory.from_config(alembic_config())


def _history() -> int:
    for rev in _scripts().walk_revisions():
        print(f"{rev.revision}  {(rev.doc or '').strip().splitlines()[0] if rev.doc else ''}")
    print("base  no schema (every table dropped)")
    return 0


def _known_revisions() -> str:
    return ", ".join(
        [walk_revision.revision for walk_revision in _scripts().walk_revisions()] + ["base"]
    )


def _named_revision(scripts: ScriptDirectory, target: str) -> str:
    """The full revision id the user's `target` names; refused, with the known ones, if none."""
    from alembic.util.exc import CommandError

    try:
        found = scripts.get_revision(target)
    except CommandError:
        found = None
    if found is None:
        raise InputError(
            f"downgrade: no revision {target!r}; name one of {_known_revisions()} "
            "(`tiltlab db history` lists them)"
        )
    return found.revision


def _revisions_undone(scripts: ScriptDirectory, current: str, target: str) -> list[str]:
    """The migrations a downgrade from `current` to `target` undoes; refused if `target` is not
    below `current`."""
    undone = [script.revision for script in scripts.iterate_revisions(current, target)]
    if target != "base":
        below = {script.revision for script in scripts.iterate_revisions(current, "base")}
        if target not in below:
            raise InputError(
                f"downgrade: revision {target} is not below the current revision {current} "
                "(`tiltlab db upgrade` moves up)"
            )
        undone = [revision for revision in undone if revision != target]
    return undone


def _downgrade(settings: Settings, engine: Engine, target: str, yes: bool) -> int:
    from service.storage.backup import (
        backup_sqlite,
        pg_dump_command,
        sqlite_path,
        timestamped_backup_path,
    )
    from service.storage.engine import redacted
    from service.storage.migrate import current_revision, downgrade

    where = redacted(settings.database_url)
    scripts = _scripts()
    if target != "base":
        target = _named_revision(scripts, target)
    current = current_revision(engine)
    if current is None:
        print(f"{where}: already at base (no schema); nothing to downgrade", file=sys.stderr)
        return 0 if target == "base" else 2
    if current == target:
        print(f"{where}: already at revision {current}; nothing to downgrade", file=sys.stderr)
        return 0
    undone = _revisions_undone(scripts, current, target)
    what = "every table" if target == "base" else "the tables of migration(s) " + ", ".join(undone)
    path = sqlite_path(settings.database_url)
    if not yes:
        backup_note = (
            "the SQLite file is backed up first"
            if path is not None
            else "PostgreSQL is not backed up by tiltlab: dump it first with "
            + pg_dump_command(settings.database_url, f"tiltlab-before-downgrade-{current}.dump")
        )
        raise InputError(
            f"downgrade from {current} to {target} drops {what} and the data in them, calibration "
            f"records included; run again with --yes to go ahead ({backup_note})"
        )
    if path is not None:
        backup = backup_sqlite(path, timestamped_backup_path(path, f"before-downgrade-{current}"))
        print(f"backed up {path} to {backup}")
    else:
        print(f"{where}: not backed up by tiltlab (PostgreSQL; --yes given)", file=sys.stderr)
    downgrade(engine, target)
    print(f"{where}: at revision {current_revision(engine) or 'none (base)'}")
    return 0


def _backup(settings: Settings, out: str) -> int:
    from service.storage.backup import backup_sqlite, pg_dump_command, sqlite_path
    from service.storage.engine import redacted

    path = sqlite_path(settings.database_url)
    if path is None:
        print(
            "tiltlab does not dump PostgreSQL itself (use the server's own pg_dump, which "
            "matches its version; the password comes from its prompt, PGPASSWORD or ~/.pgpass):",
            file=sys.stderr,
        )
        print(pg_dump_command(settings.database_url, out))
        return 0
    if not path.is_file():
        raise InputError(
            f"{redacted(settings.database_url)}: no database file at {path} to back up"
        )
    written = backup_sqlite(path, Path(out))
    print(f"backed up {path} to {written}")
    return 0


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = add_command(
        sub,
        "db",
        "database upkeep: schema upgrade, revision, backup, downgrade, verification",
        description="Upkeep of the configured database (TILTLAB_DATABASE_URL; default the SQLite "
        "file tiltlab.db\nin TILTLAB_DATA_DIR). `tiltlab serve` upgrades the schema by "
        "itself at start-up.",
        examples=[
            "tiltlab db current",
            "tiltlab db backup --out tiltlab-2026-11-23.db",
            "tiltlab db downgrade base --yes",
        ],
    )
    dbsub = add_subcommands(parser, "db_command")
    add_command(
        dbsub,
        "upgrade",
        "bring the database to the current schema (creates it if needed)",
        examples=["tiltlab db upgrade"],
    )
    add_command(
        dbsub,
        "current",
        "print the schema revision of the database (never creates one)",
        examples=["tiltlab db current"],
    )
    add_command(
        dbsub, "history", "list the schema revisions, newest first", examples=["tiltlab db history"]
    )
    command_parser = add_command(
        dbsub,
        "downgrade",
        "step the schema back to a named revision, dropping newer tables",
        description="Step the schema back to REVISION. The tables of the migrations undone are "
        "dropped with their\ndata, calibration records included: a SQLite database is "
        "first copied (online backup)\nbeside itself and the copy's path printed; for "
        "PostgreSQL the pg_dump command to run first\nis printed.",
        examples=["tiltlab db downgrade base --yes"],
    )
    command_parser.add_argument(
        "revision",
        help="the revision to go back to (see `tiltlab db history`), or base for no schema",
    )
    command_parser.add_argument(
        "--yes",
        action="store_true",
        help="go ahead: the data in the dropped tables are lost (SQLite is backed up first)",
    )
    command_parser = add_command(
        dbsub,
        "backup",
        "copy the SQLite database to a new file, also while the service runs; "
        "for PostgreSQL print the pg_dump command",
        examples=["tiltlab db backup --out /backups/tiltlab-2026-11-23.db"],
    )
    command_parser.add_argument(
        "--out", required=True, metavar="FILE", help="the backup file to write (must not exist)"
    )
    add_command(
        dbsub,
        "verify",
        "check the hashes and chains of calibration records and audit events",
        examples=["tiltlab db verify"],
    )
    parser.set_defaults(handler=run)
