"""Backups before anything destructive: SQLite through its online backup API, PostgreSQL by pg_dump.

SQLite's backup API copies a consistent snapshot while the service keeps writing (a plain file
copy of a WAL database can miss committed pages). PostgreSQL is dumped by the lab's own
`pg_dump`, which matches its server version; tiltlab prints the command rather than running a
tool it cannot vouch for.
"""

from __future__ import annotations

import datetime as _dt
import os
import shlex
import sqlite3
import tempfile
from pathlib import Path

import sqlalchemy as sa

from service.errors import InputError
from service.storage.engine import normalise_url


def sqlite_path(url: str | sa.URL) -> Path | None:
    """The database file of a SQLite URL; None for PostgreSQL. In-memory SQLite is refused."""
    db_url = normalise_url(url) if isinstance(url, str) else url
    if db_url.get_backend_name() != "sqlite":
        return None
    database = db_url.database or ""
    if database in ("", ":memory:") or database.startswith("file::memory:"):
        raise InputError(
            "the database is an in-memory SQLite database; there is no file to back up"
        )
    return Path(database).expanduser()


def database_exists(url: str | sa.URL) -> bool:
    """Whether a SQLite file is there (PostgreSQL: assumed, the server says otherwise on
    connect)."""
    try:
        path = sqlite_path(url)
    except InputError:
        return True  # in memory: exists for as long as the connection
    return path is None or path.is_file()


def backup_sqlite(source: Path, out: Path) -> Path:
    """Copy the live database `source` to the new file `out` (never replaced), atomically."""
    out = Path(out)
    if out.exists():
        raise InputError(f"{out}: already exists; give a new file name for the backup")
    if not out.parent.is_dir():
        raise InputError(f"{out}: folder {out.parent} does not exist")
    if not source.is_file():
        raise InputError(f"{source}: no database file to back up")
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent)
    os.close(fd)
    try:
        src = sqlite3.connect(f"file:{source}?mode=ro", uri=True)
        try:
            dst = sqlite3.connect(tmp)
            try:
                src.backup(dst)
                # one self-contained file, no -wal beside it
                dst.execute("PRAGMA journal_mode=DELETE")
            finally:
                dst.close()
        finally:
            src.close()
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return out


def timestamped_backup_path(source: Path, reason: str) -> Path:
    """`tiltlab.db` -> `tiltlab.db.<reason>-20261123T004512Z.bak`, beside the database."""
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    path = source.with_name(f"{source.name}.{reason}-{stamp}.bak")
    n = 1
    while path.exists():
        n += 1
        path = source.with_name(f"{source.name}.{reason}-{stamp}-{n}.bak")
    return path


def pg_dump_command(url: str | sa.URL, out: str | Path) -> str:
    """The shell command that dumps the PostgreSQL database of `url` into `out` (custom format).

    The password is never printed: pg_dump asks for it, or takes it from PGPASSWORD or ~/.pgpass.
    """
    db_url = normalise_url(url) if isinstance(url, str) else url
    parts = ["pg_dump", "--format=custom", f"--file={out}"]
    if db_url.host:
        parts.append(f"--host={db_url.host}")
    if db_url.port:
        parts.append(f"--port={db_url.port}")
    if db_url.username:
        parts.append(f"--username={db_url.username}")
    options = db_url.query.get("options")
    if isinstance(options, str) and "search_path=" in options:
        schema = options.split("search_path=", 1)[1].split()[0]
        parts.append(f"--schema={schema}")
    parts.append(db_url.database or "")
    return shlex.join(parts)
