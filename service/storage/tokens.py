"""API tokens: random, shown once, kept only as a SHA-256; scopes read < operate < admin."""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterable
from dataclasses import dataclass

from service.errors import InputError

SCOPES = ("read", "operate", "admin")
# What each scope grants: admin implies operate and read, operate implies read.
IMPLIED: dict[str, set[str]] = {"read": {"read"}, "operate": {"read", "operate"}, "admin": {"read", "operate", "admin"}}
TOKEN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._@-]{0,99}")
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
