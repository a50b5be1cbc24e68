"""`tiltlab verify-certificate FILE`: is this a certificate we issued, unchanged, resting on an
approved record?

Checks offline: validity against the DCC 3.3.0 schema and the enveloped XML signature (over the
whole file: a change of any byte fails; with --signer-cert, made by the lab's own certificate). A
file without a signature fails (a stripped signature must not read as unaltered) unless
--allow-unsigned, or the laboratory's database holds it byte for byte.
With the lab's database (TILTLAB_DATABASE_URL or the data directory's): that the file's SHA-256
equals the one stored at issue, that the stored copy still matches it, that the record still matches
its hash and that the approval is bound to it. Exit 0 when every check passes, 1 when one fails, 2
for an unreadable file or configuration.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from service.errors import InputError

if TYPE_CHECKING:
    from sqlalchemy.engine import Engine

    from service.storage.store import Store


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from service.commands._args import add_command

    parser = add_command(
        sub,
        "verify-certificate",
        "check a DCC certificate: schema, signature, stored hash, record and approval",
        examples=[
            "tiltlab verify-certificate certificate.xml",
            "tiltlab verify-certificate --offline certificate.xml",
            "tiltlab verify-certificate --offline --allow-unsigned certificate.xml",
        ],
    )
    parser.add_argument("file", metavar="FILE", help="the certificate XML file")
    parser.add_argument(
        "--offline",
        action="store_true",
        help="check only the file: schema and signature (no database: for a customer who has just "
        "the file)",
    )
    parser.add_argument(
        "--signer-cert",
        metavar="PEM",
        help="the laboratory's signing certificate: the signature must be made with it (an "
        "unsigned file then fails); without it, the certificate the signature carries is used",
    )
    parser.add_argument(
        "--allow-unsigned",
        action="store_true",
        help="accept a file without a signature (from a laboratory that does not sign); without "
        "it an unsigned file fails unless the laboratory's database holds it unchanged",
    )
    parser.set_defaults(handler=run)


def _read_file(path: Path) -> bytes:
    """The certificate's bytes, or one line saying why they cannot be read."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror}") from None


def _trusted_signer(signer_cert: str | None) -> bytes | None:
    """The lab's signing certificate given with --signer-cert, if any."""
    if not signer_cert:
        return None
    try:
        return Path(signer_cert).read_bytes()
    except OSError as exc:
        raise InputError(f"{signer_cert}: cannot read: {exc.strerror}") from None


def _open_store() -> tuple[Store, Engine]:
    """The lab's database, which must exist and have a schema, to check the file against."""
    from service.config import get_settings
    from service.storage.backup import database_exists, sqlite_path
    from service.storage.engine import make_engine, redacted
    from service.storage.migrate import current_revision
    from service.storage.store import Store

    settings = get_settings()
    where = redacted(settings.database_url)
    if not database_exists(settings.database_url):
        raise InputError(
            f"{where}: no database file at {sqlite_path(settings.database_url)};"
            " use --offline to check only the schema"
        )
    engine = make_engine(settings.database_url, busy_timeout_ms=settings.sqlite_busy_timeout_ms)
    if current_revision(engine) is None:
        engine.dispose()
        raise InputError(f"{where}: no schema yet; use --offline to check only the schema")
    return Store(engine), engine


def run(args: argparse.Namespace) -> int:
    from service.lims.certificates import verify_certificate

    path = Path(args.file)
    xml = _read_file(path)
    trusted = _trusted_signer(args.signer_cert)
    store = engine = None
    if not args.offline:
        store, engine = _open_store()
    try:
        report = verify_certificate(xml, store, trusted, allow_unsigned=args.allow_unsigned)
    finally:
        if engine is not None:
            engine.dispose()
    print(f"{path}: certificate {report.number or '(unknown)'}, SHA-256 {report.sha256}")
    for fact in report.facts:
        print(f"  ok: {fact}")
    for problem in report.problems:
        print(f"  FAILED: {problem}")
    print(
        "OK" if report.ok else f"FAILED: {len(report.problems)} problem(s)",
        file=sys.stdout if report.ok else sys.stderr,
    )
    return 0 if report.ok else 1
