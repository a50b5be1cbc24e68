"""`tiltlab token create|list|revoke`: API tokens in the configured database (shown once, kept as hashes)."""

from __future__ import annotations

import argparse
import getpass
import sys


def operator_name() -> str:
    try:
        return f"cli:{getpass.getuser()}"
    except Exception:  # noqa: BLE001 - no user name in some containers
        return "cli"


def run(args: argparse.Namespace) -> int:
    from service.config import get_settings
    from service.storage.migrate import bootstrap
    from service.storage.store import Database, TokensRepo

    engine = bootstrap(get_settings())
    tokens = TokensRepo(Database(engine))
    try:
        if args.token_command == "create":
            row, token = tokens.create_token(args.name, args.scopes, actor=operator_name())
            print(token)
            print(f"token {row.name!r} ({', '.join(row.scopes)}) created; it is shown only now", file=sys.stderr)
        elif args.token_command == "list":
            rows = tokens.all(include_revoked=args.all)
            for r in rows:
                state = f"revoked {r.revoked_at:%Y-%m-%dT%H:%M:%SZ}" if r.revoked_at else "active"
                print(f"{r.name}\t{','.join(r.scopes)}\tcreated {r.created_at:%Y-%m-%dT%H:%M:%SZ} by {r.created_by}\t{state}")
            if not rows:
                print("no tokens", file=sys.stderr)
        else:
            tokens.revoke_token(args.name, actor=operator_name())
            print(f"token {args.name!r} revoked", file=sys.stderr)
        return 0
    finally:
        engine.dispose()


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from service.commands._args import add_command, add_subcommands

    p = add_command(sub, "token", "API tokens: create (shown once), list, revoke",
                    description="API tokens for clients of the service, kept in its database as hashes.",
                    examples=["tiltlab token create --name bench-pc --scopes read,operate",
                              "tiltlab token list --all", "tiltlab token revoke bench-pc"])
    tsub = add_subcommands(p, "token_command")
    q = add_command(tsub, "create", "make a token and print it (only now)",
                    examples=["tiltlab token create --name bench-pc --scopes read,operate"])
    q.add_argument("--name", required=True, help="a name to know the token by")
    q.add_argument("--scopes", required=True, help="comma-separated: read, operate, admin (admin implies the others)")
    q = add_command(tsub, "list", "tokens by name and scopes (never the tokens themselves)",
                    examples=["tiltlab token list"])
    q.add_argument("--all", action="store_true", help="also revoked tokens")
    q = add_command(tsub, "revoke", "revoke a token by name", examples=["tiltlab token revoke bench-pc"])
    q.add_argument("name", help="the token's name")
    p.set_defaults(handler=lambda a: run(a))
