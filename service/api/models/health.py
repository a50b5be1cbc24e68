"""Bodies of /health and /ready."""

from __future__ import annotations

import datetime as dt
from typing import Literal

from pydantic import Field

from service.api.models.base import Answer


class DatabaseOutageState(Answer):
    away_since_utc: dt.datetime = Field(
        description="when the daemon first found the database unreachable"
    )
    away_s: float = Field(description="seconds the database has been unreachable")
    error: str | None = Field(description="the database's (or the connection's) last words")
    outage_limit_s: float = Field(
        description="TILTLAB_DB_OUTAGE_S: a job waiting longer than this fails"
        " (database_unreachable)"
    )
    jobs_waiting: list[int] = Field(
        description="jobs whose next step waits for the database (paused)"
    )
    writes_waiting: int = Field(description="database writes waiting for the database to answer")
    samples_waiting: int = Field(
        description="raw samples held in memory by those writes; stored once it answers"
    )


class DiskState(Answer):
    folder: str = Field(
        description="a folder the daemon writes (the data directory, an SQLite database's folder)"
    )
    free_mb: float = Field(description="free space on its disk, MB (10^6 bytes)")
    min_free_mb: float = Field(
        description="TILTLAB_MIN_FREE_MB: below it jobs do not start and running ones stop"
    )
    full: bool = Field(description="less free than min_free_mb")


class Health(Answer):
    status: Literal["ok", "degraded"] = Field(
        description="degraded when the database schema is not at head,"
        " the database is unreachable or a disk is full"
    )
    version: str
    database: str = Field(description="the database URL without its password")
    database_state: Literal["up", "away"] = Field(
        description="away while the daemon finds the database unreachable (it goes on serving "
        "its benches; writes wait); checked at most once a second"
    )
    database_outage: DatabaseOutageState | None = Field(
        description="while the database is away: since when, and what waits for it"
    )
    schema_revision: str | None
    bench: str = Field(description="the bench, or the benches joined by commas")
    benches: list[str]
    disk: list[DiskState] = Field(
        default_factory=list, description="free space of the folders the daemon writes"
    )
    jobs_not_stored: list[int] = Field(
        default_factory=list,
        description="jobs whose end could not be stored (a full disk): written once there is room",
    )


class Readiness(Answer):
    ready: bool
    reasons: list[str] = Field(description="why not ready, one line each")
