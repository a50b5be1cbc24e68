"""API tokens: random, shown once, kept only as a SHA-256 (the rules in
service/storage/tokens.py)."""

from __future__ import annotations

import secrets
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TypedDict

import sqlalchemy as sa

from service.errors import InputError
from service.storage.errors import ConflictError, UnknownEntity
from service.storage.models import ApiToken, AuditEvent, utc_now
from service.storage.store.database import Database
from service.storage.tokens import (
    TOKEN_NAME,
    TOKEN_PREFIX,
    NamedPerson,
    Person,
    Principal,
    granted,
    parse_scopes,
    token_sha256,
)

FIRST_ADMIN_NAME = "admin"
FIRST_START_ACTOR = "daemon first start"


@dataclass(frozen=True)
class FirstAdminToken:
    """Where the lab's first admin token was written and by which daemon (its text is never
    kept)."""

    node: str
    file: str


class TokensRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def create_token(
        self, name: str, scopes: str | Iterable[str], *, actor: str, person: Person | None = None
    ) -> tuple[ApiToken, str]:
        """A new token (belonging to `person`, when given): returns its row and the token text,
        which is not kept anywhere."""
        if not isinstance(name, str) or not TOKEN_NAME.fullmatch(name):
            raise InputError(
                f"token name {name!r}: 1-100 letters, digits, '.', '_', '@' or '-', starting with "
                "a letter or digit"
            )
        scope_list = parse_scopes(scopes)
        token = TOKEN_PREFIX + secrets.token_urlsafe(32)
        with self._db.transaction() as session:
            if session.scalar(sa.select(ApiToken.id).where(ApiToken.name == name)) is not None:
                raise ConflictError(f"a token named {name!r} already exists (revoke it first)")
            row = ApiToken(
                name=name,
                token_sha256=token_sha256(token),
                scopes=scope_list,
                created_at=utc_now(),
                created_by=actor,
                person_name=person.name if person else None,
                person_function=person.function if person else None,
            )
            session.add(row)
            session.flush()
            self._db.audit(
                session,
                actor,
                "token.create",
                "api_token",
                name,
                {"scopes": scope_list, **_person_details(person)},
            )
            return row, token

    def set_person(self, name: str, person: Person, *, actor: str) -> ApiToken:
        """The person an active token belongs to, set or changed (audited with the previous one)."""
        with self._db.transaction() as session:
            row = session.scalar(
                sa.select(ApiToken).where(ApiToken.name == name, ApiToken.revoked_at.is_(None))
            )
            if row is None:
                raise UnknownEntity(f"no active token named {name!r}")
            before = person_of_row(row)
            row.person_name, row.person_function = person.name, person.function
            self._db.audit(
                session,
                actor,
                "token.person",
                "api_token",
                name,
                {
                    **_person_details(person),
                    "previous_person": _person_details(before).get("person"),
                },
            )
            return row

    def create_first_admin_token(
        self, *, node: str, file: str, write: Callable[[str], object]
    ) -> str | None:
        """The lab's first admin token, made only while the database holds no token at all.

        Daemons starting together on a new database take turns (write transactions are serialised):
        the first makes the token and gets its text, every other one finds it made and gets None.
        The token is handed to `write` (which keeps it in `file`) before the transaction commits, so
        a token that could not be written is not kept either, and the next start tries again."""
        token = TOKEN_PREFIX + secrets.token_urlsafe(32)
        with self._db.transaction() as session:
            if session.scalar(sa.select(ApiToken.id).limit(1)) is not None:
                return None
            session.add(
                ApiToken(
                    name=FIRST_ADMIN_NAME,
                    token_sha256=token_sha256(token),
                    scopes=["admin"],
                    created_at=utc_now(),
                    created_by=FIRST_START_ACTOR,
                )
            )
            session.flush()
            self._db.audit(
                session,
                FIRST_START_ACTOR,
                "token.create",
                "api_token",
                FIRST_ADMIN_NAME,
                {"scopes": ["admin"], "node": node, "file": file},
            )
            write(token)
            return token

    def first_admin_token(self) -> FirstAdminToken | None:
        """Which daemon wrote the lab's first admin token, and where (None for a database that has
        none, or whose first token was made before daemons recorded this)."""
        with self._db.session() as session:
            details = session.scalar(
                sa.select(AuditEvent.details)
                .where(
                    AuditEvent.action == "token.create",
                    AuditEvent.entity == "api_token",
                    AuditEvent.actor == FIRST_START_ACTOR,
                )
                .order_by(AuditEvent.id)
                .limit(1)
            )
        if (
            not details
            or not isinstance(details.get("file"), str)
            or not isinstance(details.get("node"), str)
        ):
            return None
        return FirstAdminToken(node=details["node"], file=details["file"])

    def all(self, *, include_revoked: bool = False) -> list[ApiToken]:
        with self._db.session() as session:
            stmt = sa.select(ApiToken).order_by(ApiToken.id)
            if not include_revoked:
                stmt = stmt.where(ApiToken.revoked_at.is_(None))
            return list(session.scalars(stmt))

    def page(
        self, *, include_revoked: bool = False, after_id: int | None = None, limit: int = 50
    ) -> list[ApiToken]:
        """Tokens in the order they were made from after `after_id` (the cursor), at most
        `limit`."""
        with self._db.session() as session:
            stmt = sa.select(ApiToken).order_by(ApiToken.id).limit(limit)
            if not include_revoked:
                stmt = stmt.where(ApiToken.revoked_at.is_(None))
            if after_id is not None:
                stmt = stmt.where(ApiToken.id > after_id)
            return list(session.scalars(stmt))

    def has_tokens(self) -> bool:
        with self._db.session() as session:
            return (session.scalar(sa.select(sa.func.count()).select_from(ApiToken)) or 0) > 0

    def revoke_token(self, name: str, *, actor: str) -> ApiToken:
        with self._db.transaction() as session:
            row = session.scalar(
                sa.select(ApiToken).where(ApiToken.name == name, ApiToken.revoked_at.is_(None))
            )
            if row is None:
                raise UnknownEntity(f"no active token named {name!r}")
            # JSON lists of scopes: counted here, the same on every database
            if "admin" in row.scopes:
                others = session.scalars(
                    sa.select(ApiToken.scopes).where(
                        ApiToken.revoked_at.is_(None), ApiToken.id != row.id
                    )
                )
                admins = sum(1 for scopes in others if "admin" in scopes)
                if admins == 0:
                    raise ConflictError(
                        f"{name!r} is the last admin token: revoking it would lock everyone out of"
                        " administration (tokens, webhooks, standards, approvals); create another"
                        " admin token first"
                    )
            row.revoked_at = utc_now()
            self._db.audit(session, actor, "token.revoke", "api_token", name, {})
            return row

    def authenticate(self, token: str) -> Principal | None:
        """The principal of a presented token, or None for an unknown or revoked one."""
        if not token:
            return None
        with self._db.session() as session:
            row = session.scalar(
                sa.select(ApiToken).where(
                    ApiToken.token_sha256 == token_sha256(token), ApiToken.revoked_at.is_(None)
                )
            )
        if row is None:
            return None
        return Principal(row.name, frozenset(granted(row.scopes)), person_of_row(row))

    def person_of_token(self, name: str) -> Person | None:
        """The person a token (active or revoked) names now, None for a token without one or no such
        token."""
        with self._db.session() as session:
            row = session.scalar(sa.select(ApiToken).where(ApiToken.name == name))
        return person_of_row(row) if row is not None else None


def person_of_row(row: ApiToken) -> Person | None:
    return Person(row.person_name, row.person_function) if row.person_name else None


class PersonDetails(TypedDict, total=False):
    """An audit event's details about the person behind a token (none: no person)."""

    person: NamedPerson


def _person_details(person: Person | None) -> PersonDetails:
    """How the audit trail names a person."""
    return {} if person is None else {"person": {"name": person.name, "function": person.function}}
