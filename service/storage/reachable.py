"""Waiting for the database at start-up: a PostgreSQL server that is still starting (a container
brought up beside it, a lab server rebooting) is retried with back-off for a set time, saying
so; a refusal that waiting cannot cure (wrong password, no such database) is reported at once."""

from __future__ import annotations

from collections.abc import Callable

import sqlalchemy as sa

from service.clock import REAL_TIME, Clock
from service.errors import InputError
from service.storage.engine import redacted

# SQLSTATE classes that no amount of waiting mends: authorisation (28xxx), unknown database (3D000).
_CONFIGURATION_SQLSTATES = ("28", "3D")
# At connection time libpq often gives no SQLSTATE, only the server's FATAL text; these mend by
# waiting.
_TRANSIENT_FATAL = (
    "starting up",
    "shutting down",
    "in recovery",
    "too many",
    "remaining connection slots",
)


class DatabaseUnreachable(RuntimeError):
    """The database did not answer within the time allowed."""


def _refused_by_server(exc: BaseException) -> bool:
    """The server answered and refused (credentials, database name): waiting will not help."""
    orig = getattr(exc, "orig", None)
    state = getattr(orig, "sqlstate", None) or ""
    if state:
        return state.startswith(_CONFIGURATION_SQLSTATES)
    text = str(orig or exc)
    return "FATAL:" in text and not any(t in text for t in _TRANSIENT_FATAL)


def _reason(exc: BaseException) -> str:
    orig = getattr(exc, "orig", None) or exc
    text = " ".join(str(orig).split())
    return text[:300] or type(orig).__name__


def wait_for_database(
    engine: sa.Engine,
    wait_s: float,
    say: Callable[[str], None],
    *,
    clock: Clock = REAL_TIME,
    setting: str = "TILTLAB_DATABASE_URL",
) -> None:
    """Return once `SELECT 1` succeeds; retry connection failures with back-off for `wait_s`
    seconds.

    Raises InputError when the server refuses the credentials or the database name (configuration),
    DatabaseUnreachable when it has not answered after `wait_s`.
    """
    where = redacted(engine.url)
    start = clock.monotonic()
    delay_s = 0.25
    said = False
    while True:
        try:
            with engine.connect() as conn:
                conn.execute(sa.text("SELECT 1"))
            if said:
                say(f"database {where} answered after {clock.monotonic() - start:.1f} s")
            return
        except sa.exc.OperationalError as exc:
            if _refused_by_server(exc):
                raise InputError(
                    f"{setting} ({where}): the server refused: {_reason(exc)}; "
                    "correct the user, password or database name"
                ) from None
            left_s = wait_s - (clock.monotonic() - start)
            if left_s <= 0:
                raise DatabaseUnreachable(
                    f"{setting} ({where}): no answer after {wait_s:g} s ({_reason(exc)}); start "
                    "the database "
                    "server or correct the URL (TILTLAB_DATABASE_WAIT_S sets how long to wait)"
                ) from None
            if not said:
                say(
                    f"database {where} not reachable ({_reason(exc)}); retrying for up to "
                    f"{wait_s:g} s"
                )
                said = True
            clock.sleep_blocking(min(delay_s, left_s))
            delay_s = min(delay_s * 2, 5.0)
