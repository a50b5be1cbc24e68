"""`tiltlab db upgrade|current|downgrade [revision]|verify` on the configured database."""

from __future__ import annotations

import argparse
import sys

from service.config import get_settings
from service.storage.engine import make_engine, redacted
from service.storage.migrate import current_revision, downgrade, head_revision


def run(args: argparse.Namespace) -> int:
    settings = get_settings()
    command = args.db_command
    if command == "upgrade":
        from service.storage.migrate import bootstrap

        engine = bootstrap(settings)
        print(f"{redacted(settings.database_url)}: at revision {current_revision(engine)} (head)")
        return 0
    engine = make_engine(settings.database_url, busy_timeout_ms=settings.sqlite_busy_timeout_ms)
    try:
        if command == "current":
            rev = current_revision(engine)
            head = head_revision()
            state = "empty, run `tiltlab db upgrade`" if rev is None else ("head" if rev == head else f"head is {head}")
            print(f"{redacted(settings.database_url)}: revision {rev or 'none'} ({state})")
            return 0
        if command == "downgrade":
            downgrade(engine, args.revision)
            print(f"{redacted(settings.database_url)}: at revision {current_revision(engine) or 'none (base)'}")
            return 0
        if command == "verify":
            from service.storage.verify import verify

            if current_revision(engine) is None:
                print(f"{redacted(settings.database_url)}: no schema yet (run `tiltlab db upgrade`)", file=sys.stderr)
                return 1
            report = verify(engine)
            for line in report.lines():
                print(line)
            return 0 if report.ok else 1
        raise ValueError(f"unknown db command {command!r}")
    finally:
        engine.dispose()
