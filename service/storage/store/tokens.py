"""API tokens: random, shown once, kept only as a SHA-256 (the rules in service/storage/tokens.py)."""

from __future__ import annotations

import secrets
from collections.abc import Iterable

import sqlalchemy as sa

from service.errors import InputError
from service.storage.errors import ConflictError, UnknownEntity
from service.storage.models import ApiToken, utc_now
from service.storage.store.database import Database
from service.storage.tokens import TOKEN_NAME, TOKEN_PREFIX, Principal, granted, parse_scopes, token_sha256


class TokensRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def create_token(self, name: str, scopes: str | Iterable[str], *, actor: str) -> tuple[ApiToken, str]:
        """A new token: returns its row and the token text, which is not kept anywhere."""
        if not isinstance(name, str) or not TOKEN_NAME.fullmatch(name):
            raise InputError(f"token name {name!r}: 1-100 letters, digits, '.', '_', '@' or '-', starting with a letter or digit")
        scope_list = parse_scopes(scopes)
        token = TOKEN_PREFIX + secrets.token_urlsafe(32)
        with self._db.transaction() as s:
            if s.scalar(sa.select(ApiToken.id).where(ApiToken.name == name)) is not None:
                raise ConflictError(f"a token named {name!r} already exists (revoke it first)")
            row = ApiToken(name=name, token_sha256=token_sha256(token), scopes=scope_list, created_at=utc_now(),
                           created_by=actor)
            s.add(row)
            s.flush()
            self._db.audit(s, actor, "token.create", "api_token", name, {"scopes": scope_list})
            return row, token

    def all(self, *, include_revoked: bool = False) -> list[ApiToken]:
        with self._db.session() as s:
            stmt = sa.select(ApiToken).order_by(ApiToken.id)
            if not include_revoked:
                stmt = stmt.where(ApiToken.revoked_at.is_(None))
            return list(s.scalars(stmt))

    def has_tokens(self) -> bool:
        with self._db.session() as s:
            return (s.scalar(sa.select(sa.func.count()).select_from(ApiToken)) or 0) > 0

    def revoke_token(self, name: str, *, actor: str) -> ApiToken:
        with self._db.transaction() as s:
            row = s.scalar(sa.select(ApiToken).where(ApiToken.name == name, ApiToken.revoked_at.is_(None)))
            if row is None:
                raise UnknownEntity(f"no active token named {name!r}")
            row.revoked_at = utc_now()
            self._db.audit(s, actor, "token.revoke", "api_token", name, {})
            return row

    def authenticate(self, token: str) -> Principal | None:
        """The principal of a presented token, or None for an unknown or revoked one."""
        if not token:
            return None
        with self._db.session() as s:
            row = s.scalar(sa.select(ApiToken).where(ApiToken.token_sha256 == token_sha256(token),
                                                     ApiToken.revoked_at.is_(None)))
        if row is None:
            return None
        return Principal(row.name, frozenset(granted(row.scopes)))
