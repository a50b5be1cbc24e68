"""The database going away while the daemon runs: telling an outage from a refusal, and waiting it
out.

An outage is a database that does not answer (connection refused or reset, the server shutting
down, a connection invalidated mid-transaction); it mends by waiting. Everything else a database
says (a constraint, a lock timeout, a bad statement) is an answer and is raised at once.

`DatabaseState` is what the daemon knows of its database (up, or away since when and why; how
many writes wait); `through_outage` runs a write again, with back-off, while the database is away,
and gives up with `DatabaseOutage` once the outage has lasted `outage_s`. A write passed to it is
run again after a failure whose outcome is unknown (a COMMIT sent, its answer lost): it must be
safe to repeat (see `samples.insert_samples_once` and the job manager's writes).
"""

from __future__ import annotations

import asyncio
import datetime as dt
import logging
import threading
import time
from collections.abc import Awaitable, Callable
from typing import TypeVar

import sqlalchemy as sa

log = logging.getLogger("tiltlab.storage")
T = TypeVar("T")

# SQLSTATEs that mean "the server is going or gone", not "the server refused this": connection
# exceptions (class 08), administrator/crash shutdown and "cannot connect now" (57P01-57P03).
_AWAY_SQLSTATES = ("08", "57P01", "57P02", "57P03")
# A server that answers FATAL at connection time refuses for good (password, database name) unless
# it says these.
_TRANSIENT_FATAL = (
    "starting up",
    "shutting down",
    "in recovery",
    "too many",
    "remaining connection slots",
)
BACKOFF_FIRST_S = 0.25
BACKOFF_MAX_S = 2.0


class DatabaseOutage(RuntimeError):
    """The database stayed unreachable for longer than the daemon waits (`TILTLAB_DB_OUTAGE_S`)."""


def unreachable(exc: BaseException) -> bool:
    """Whether an exception means the database is away (waiting mends it), not that it refused
    something."""
    if isinstance(exc, DatabaseOutage):
        return True
    if not isinstance(exc, sa.exc.DBAPIError):
        return False
    if exc.connection_invalidated:
        return True
    if not isinstance(exc, sa.exc.OperationalError):
        return False
    orig = exc.orig
    module = type(orig).__module__ or ""
    if module.startswith("sqlite3"):
        return False  # "database is locked" and the like: SQLite has no server to lose
    state = getattr(orig, "sqlstate", None)
    if state is None:  # the client's own failure: refused, reset, closed by the server, timed out
        text = str(orig)
        return "FATAL:" not in text or any(t in text for t in _TRANSIENT_FATAL)
    return str(state).startswith(_AWAY_SQLSTATES)


def reason_of(exc: BaseException) -> str:
    """The database's own words, one line."""
    orig = getattr(exc, "orig", None) or exc
    text = " ".join(str(orig).split())
    return text[:300] or type(orig).__name__


class DatabaseState:
    """Whether the database answers, as the daemon last found it; shared by its writers and
    /health."""

    def __init__(self, where: str, outage_s: float = 300.0) -> None:
        self.where = where  # the database URL without its password
        self.outage_s = outage_s
        self._lock = threading.Lock()
        self._away_since: float | None = None  # monotonic seconds
        self.away_since_utc: dt.datetime | None = None
        self.error: str | None = None
        self.writes_waiting = 0  # writes (job steps) waiting for the database to come back
        self.samples_waiting = 0  # the raw samples those writes hold in memory meanwhile
        self.outages = 0  # outages seen since start

    @property
    def up(self) -> bool:
        return self._away_since is None

    def away_for_s(self) -> float:
        since = self._away_since
        return 0.0 if since is None else time.monotonic() - since

    def away(self, exc: BaseException) -> None:
        with self._lock:
            self.error = reason_of(exc)
            if self._away_since is None:
                self._away_since = time.monotonic()
                self.away_since_utc = dt.datetime.now(dt.UTC)
                self.outages += 1
                log.warning(
                    "database %s unreachable (%s): writes wait for it for up to %g s",
                    self.where,
                    self.error,
                    self.outage_s,
                )

    def back(self) -> None:
        if self._away_since is None:
            return
        with self._lock:
            if self._away_since is not None:
                log.warning("database %s answers again after %.1f s", self.where, self.away_for_s())
            self._away_since, self.away_since_utc, self.error = None, None, None

    def waiting(self, delta: int, samples: int = 0) -> None:
        with self._lock:
            self.writes_waiting += delta
            self.samples_waiting += delta * samples

    def outage_error(self) -> DatabaseOutage:
        return DatabaseOutage(
            f"database_unreachable: the database {self.where} did not answer for more than"
            f" {self.outage_s:g} s (TILTLAB_DB_OUTAGE_S): {self.error}"
        )


async def _back_off(state: DatabaseState, delay_s: float, give_up: bool) -> None:
    """One back-off pause of a waiting write, never past the outage's end when it gives up."""
    left_s = state.outage_s - state.away_for_s()
    if give_up and left_s <= 0:
        raise state.outage_error() from None
    await asyncio.sleep(max(0.01, min(delay_s, left_s) if give_up else delay_s))


async def through_outage(
    state: DatabaseState,
    attempt: Callable[[], Awaitable[T]],
    *,
    on_wait: Callable[[bool], None] | None = None,
    give_up: bool = True,
    samples: int = 0,
) -> T:
    """`attempt()`, run again with back-off while the database is away.

    `on_wait(True)` once when the write starts waiting, `on_wait(False)` when it stops (written,
    given up or cancelled); `samples` is how many raw samples the write holds (for /health).
    With `give_up`, raises `DatabaseOutage` once the outage (counted from when the daemon first
    found the database away) has lasted `state.outage_s`; without it, waits for as long as it
    takes (or until cancelled).
    """
    delay_s = BACKOFF_FIRST_S
    waiting = False
    try:
        while True:
            try:
                result = await attempt()
            except Exception as exc:
                if not unreachable(exc) or isinstance(exc, DatabaseOutage):
                    raise
                state.away(exc)
                if not waiting:
                    waiting = True
                    state.waiting(+1, samples)
                    if on_wait is not None:
                        on_wait(True)
                await _back_off(state, delay_s, give_up)
                delay_s = min(delay_s * 2, BACKOFF_MAX_S)
                continue
            state.back()
            return result
    finally:
        if waiting:
            state.waiting(-1, samples)
            if on_wait is not None:
                on_wait(False)
