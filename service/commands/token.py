"""`tiltlab token create|list|set-person|revoke`: API tokens in the configured database (shown once,
kept as hashes), each optionally naming the person it belongs to (who approves or runs calibrations
with it)."""

from __future__ import annotations

import argparse
import getpass
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from service.storage.tokens import Person


def operator_name() -> str:
    try:
        return f"cli:{getpass.getuser()}"
    except Exception:  # noqa: BLE001 - no user name in some containers
        return "cli"


def run(args: argparse.Namespace) -> int:
    from service.config import get_settings
    from service.storage.migrate import bootstrap
    from service.storage.store import Database, TokensRepo
    from service.storage.store.tokens import person_of_row

    person = _person(args)
    engine = bootstrap(get_settings())
    tokens = TokensRepo(Database(engine))
    try:
        if args.token_command == "create":
            row, token = tokens.create_token(
                args.name, args.scopes, actor=operator_name(), person=person
            )
            print(token)
            whose = f", belonging to {person.described()}" if person is not None else ""
            print(
                f"token {row.name!r} ({', '.join(row.scopes)}){whose} created; it is shown only "
                "now",
                file=sys.stderr,
            )
        elif args.token_command == "list":
            rows = tokens.all(include_revoked=args.all)
            for entry in rows:
                state = (
                    f"revoked {entry.revoked_at:%Y-%m-%dT%H:%M:%SZ}"
                    if entry.revoked_at
                    else "active"
                )
                holder = person_of_row(entry)
                print(
                    f"{entry.name}\t{','.join(entry.scopes)}\t"
                    f"created {entry.created_at:%Y-%m-%dT%H:%M:%SZ} by {entry.created_by}\t"
                    f"{state}\t{holder.described() if holder else 'no person'}"
                )
            if not rows:
                print("no tokens", file=sys.stderr)
        elif args.token_command == "set-person":
            assert person is not None  # required by the parser
            row = tokens.set_person(args.name, person, actor=operator_name())
            print(f"token {row.name!r} belongs to {person.described()}", file=sys.stderr)
        else:
            tokens.revoke_token(args.name, actor=operator_name())
            print(f"token {args.name!r} revoked", file=sys.stderr)
        return 0
    finally:
        engine.dispose()


def _person(args: argparse.Namespace) -> Person | None:
    """The person the options name (--person-name, --person-function), checked; None when not
    given."""
    from service.errors import InputError
    from service.storage.tokens import person_of

    name, function = getattr(args, "person_name", None), getattr(args, "person_function", None)
    if name is None:
        if function is not None:
            raise InputError("--person-function: give --person-name with it")
        return None
    fields = {"name": name, **({"function": function} if function is not None else {})}
    try:
        return person_of(fields, "--person")
    except InputError as exc:
        raise InputError(str(exc).replace("--person.", "--person-")) from None


def _person_options(q: argparse.ArgumentParser, *, required: bool) -> None:
    q.add_argument(
        "--person-name",
        required=required,
        metavar="NAME",
        help="full name of the person the token belongs to (certificates name who approved and "
        "who ran a calibration)",
    )
    q.add_argument(
        "--person-function",
        metavar="FUNCTION",
        help='their function in the laboratory, e.g. "Head of Laboratory" (approving records needs '
        "it)",
    )


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from service.commands._args import add_command, add_subcommands

    parser = add_command(
        sub,
        "token",
        "API tokens: create (shown once), list, set-person, revoke",
        description="API tokens for clients of the service, kept in its database as hashes.",
        examples=[
            "tiltlab token create --name bench-pc --scopes read,operate",
            (
                'tiltlab token create --name alice --scopes admin --person-name "Dr. Alice '
                'Example" --person-function "Head of Laboratory"'
            ),
            "tiltlab token list --all",
            "tiltlab token revoke bench-pc",
        ],
    )
    tsub = add_subcommands(parser, "token_command")
    command_parser = add_command(
        tsub,
        "create",
        "make a token and print it (only now)",
        examples=["tiltlab token create --name bench-pc --scopes read,operate"],
    )
    command_parser.add_argument("--name", required=True, help="a name to know the token by")
    command_parser.add_argument(
        "--scopes",
        required=True,
        help="comma-separated: read, operate, admin (admin implies the others)",
    )
    _person_options(command_parser, required=False)
    command_parser = add_command(
        tsub,
        "list",
        "tokens by name and scopes (never the tokens themselves)",
        examples=["tiltlab token list"],
    )
    command_parser.add_argument("--all", action="store_true", help="also revoked tokens")
    command_parser = add_command(
        tsub,
        "set-person",
        "name the person a token belongs to",
        examples=[
            (
                'tiltlab token set-person admin --person-name "Dr. Alice Example" '
                '--person-function "Head of Laboratory"'
            )
        ],
    )
    command_parser.add_argument("name", help="the token's name")
    _person_options(command_parser, required=True)
    command_parser = add_command(
        tsub, "revoke", "revoke a token by name", examples=["tiltlab token revoke bench-pc"]
    )
    command_parser.add_argument("name", help="the token's name")
    parser.set_defaults(handler=lambda a: run(a))
