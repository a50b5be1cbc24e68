"""A full disk: telling it from other failures, and noticing it before a write meets it.

The daemon keeps `TILTLAB_MIN_FREE_MB` free in its data directory (and in the folder of an SQLite
database kept elsewhere): below that, `/ready` says so, a job does not start and a running job
stops, resumable, before the disk is full. A write that meets a full disk anyway (SQLite's
"database or disk is full", PostgreSQL's SQLSTATE 53100, an OSError ENOSPC) is a `DiskFull`,
answered 507 naming the disk, never a 500.
"""

from __future__ import annotations

import errno
import shutil
import sqlite3
from dataclasses import dataclass
from pathlib import Path

import sqlalchemy as sa
from sqlalchemy.engine import make_url

MB = 1_000_000
_SQLITE_FULL = getattr(sqlite3, "SQLITE_FULL", 13)
_PG_DISK_FULL = "53100"


class DiskFull(OSError):
    """No room to write: the disk named is full (or below the free space the daemon keeps)."""


def disk_full(exc: BaseException) -> bool:
    """Whether an exception means a full disk (the daemon's or the database server's)."""
    if isinstance(exc, DiskFull):
        return True
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    orig = getattr(exc, "orig", None) if isinstance(exc, sa.exc.DBAPIError) else None
    if orig is None:
        return False
    if getattr(orig, "sqlite_errorcode", None) == _SQLITE_FULL or "database or disk is full" in str(
        orig
    ):
        return True
    return getattr(orig, "sqlstate", None) == _PG_DISK_FULL or "No space left on device" in str(
        orig
    )


def folders_of(data_dir: Path, database_url: str) -> list[Path]:
    """The folders whose disk the daemon writes: its data directory, and an SQLite database's
    folder."""
    folders = [Path(data_dir)]
    url = make_url(database_url)
    if (
        url.get_backend_name() == "sqlite"
        and url.database
        and not url.database.startswith(":memory:")
        and not url.database.startswith("file::memory:")
    ):
        folder = Path(url.database).expanduser().parent
        if folder.resolve() != Path(data_dir).resolve():
            folders.append(folder)
    return folders


@dataclass(frozen=True)
class Space:
    folder: Path
    free_bytes: int

    @property
    def free_mb(self) -> float:
        return self.free_bytes / MB


class DiskWatch:
    """The free space of the folders the daemon writes, against the least it keeps
    (`min_free_mb`)."""

    def __init__(self, folders: list[Path], min_free_mb: float) -> None:
        self.folders = folders
        self.min_free_mb = min_free_mb

    def spaces(self) -> list[Space]:
        out = []
        for folder in self.folders:
            try:
                out.append(Space(folder, shutil.disk_usage(folder).free))
            except OSError:
                continue  # a folder not made yet: its writes will say so themselves
        return out

    def short(self) -> Space | None:
        """The folder with less free space than the daemon keeps (the emptiest of them), or None."""
        low = [space for space in self.spaces() if space.free_mb < self.min_free_mb]
        return min(low, key=lambda space: space.free_bytes) if low else None

    def reason(self, space: Space) -> str:
        return (
            f"disk full: {space.free_mb:.1f} MB free on {space.folder} (the daemon keeps at least"
            f" {self.min_free_mb:g} MB free: TILTLAB_MIN_FREE_MB)"
        )

    def check(self) -> None:
        """DiskFull naming the folder when one has less free space than the daemon keeps."""
        space = self.short()
        if space is not None:
            raise DiskFull(errno.ENOSPC, self.reason(space))

    def described(self, exc: BaseException) -> str:
        """A full-disk failure in words naming the disk: the emptiest folder's free space, or the
        database's."""
        if isinstance(exc, DiskFull) and exc.strerror:
            return exc.strerror
        spaces = self.spaces()
        emptiest = min(spaces, key=lambda s: s.free_bytes) if spaces else None
        where = (
            f"{emptiest.free_mb:.1f} MB free on {emptiest.folder}"
            if emptiest is not None
            else "the data directory"
        )
        orig = getattr(exc, "orig", None) or exc
        said = " ".join(str(orig).split())[:200]
        return f"disk full: {where} ({said})"
