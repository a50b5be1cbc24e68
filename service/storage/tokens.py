"""API tokens: random, shown once, kept only as a SHA-256; scopes read < operate < admin."""

from __future__ import annotations

import hashlib
import re
import secrets
from collections.abc import Iterable
from dataclasses import dataclass

import sqlalchemy as sa

from service.errors import InputError
from service.storage.errors import ConflictError, UnknownEntity
from service.storage.models import ApiToken, utc_now
from service.storage.store.base import StoreBase

SCOPES = ("read", "operate", "admin")
# What each scope grants: admin implies operate and read, operate implies read.
IMPLIED = {"read": {"read"}, "operate": {"read", "operate"}, "admin": {"read", "operate", "admin"}}
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._@-]{0,99}")
TOKEN_PREFIX = "tl_"


def token_sha256(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def parse_scopes(scopes: str | Iterable[str]) -> list[str]:
    items = [s.strip() for s in (scopes.split(",") if isinstance(scopes, str) else scopes)]
    items = [s for s in items if s]
    if not items:
        raise InputError(f"scopes: give at least one of {', '.join(SCOPES)}")
    unknown = [s for s in items if s not in SCOPES]
    if unknown:
        raise InputError(f"scopes: {', '.join(unknown)} unknown; scopes are {', '.join(SCOPES)}")
    return [s for s in SCOPES if s in items]


def granted(scopes: Iterable[str]) -> set[str]:
    out: set[str] = set()
    for s in scopes:
        out |= IMPLIED.get(s, set())
    return out


@dataclass(frozen=True)
class Principal:
    """Who a request is: the token's name and what it may do."""

    name: str
    scopes: frozenset[str]

    def may(self, scope: str) -> bool:
        return scope in self.scopes


class TokenStore(StoreBase):
    def create_token(self, name: str, scopes: str | Iterable[str], *, actor: str) -> tuple[ApiToken, str]:
        """A new token: returns its row and the token text, which is not kept anywhere."""
        if not isinstance(name, str) or not _NAME.fullmatch(name):
            raise InputError(f"token name {name!r}: 1-100 letters, digits, '.', '_', '@' or '-', starting with a letter or digit")
        scope_list = parse_scopes(scopes)
        token = TOKEN_PREFIX + secrets.token_urlsafe(32)
        with self._tx() as s:
            if s.scalar(sa.select(ApiToken.id).where(ApiToken.name == name)) is not None:
                raise ConflictError(f"a token named {name!r} already exists (revoke it first)")
            row = ApiToken(name=name, token_sha256=token_sha256(token), scopes=scope_list, created_at=utc_now(),
                           created_by=actor)
            s.add(row)
            s.flush()
            self._audit(s, actor, "token.create", "api_token", name, {"scopes": scope_list})
            return row, token

    def tokens(self, *, include_revoked: bool = False) -> list[ApiToken]:
        with self._read() as s:
            stmt = sa.select(ApiToken).order_by(ApiToken.id)
            if not include_revoked:
                stmt = stmt.where(ApiToken.revoked_at.is_(None))
            return list(s.scalars(stmt))

    def has_tokens(self) -> bool:
        with self._read() as s:
            return (s.scalar(sa.select(sa.func.count()).select_from(ApiToken)) or 0) > 0

    def revoke_token(self, name: str, *, actor: str) -> ApiToken:
        with self._tx() as s:
            row = s.scalar(sa.select(ApiToken).where(ApiToken.name == name, ApiToken.revoked_at.is_(None)))
            if row is None:
                raise UnknownEntity(f"no active token named {name!r}")
            row.revoked_at = utc_now()
            self._audit(s, actor, "token.revoke", "api_token", name, {})
            return row

    def authenticate(self, token: str) -> Principal | None:
        """The principal of a presented token, or None for an unknown or revoked one."""
        if not token:
            return None
        with self._read() as s:
            row = s.scalar(sa.select(ApiToken).where(ApiToken.token_sha256 == token_sha256(token),
                                                     ApiToken.revoked_at.is_(None)))
        if row is None:
            return None
        return Principal(row.name, frozenset(granted(row.scopes)))
