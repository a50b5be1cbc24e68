"""API tokens: random, shown once, kept only as a SHA-256; scopes read < operate < admin."""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TypedDict

from service.errors import InputError

SCOPES = ("read", "operate", "admin")
# What each scope grants: admin implies operate and read, operate implies read.
IMPLIED: dict[str, set[str]] = {
    "read": {"read"},
    "operate": {"read", "operate"},
    "admin": {"read", "operate", "admin"},
}
TOKEN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._@-]{0,99}")
TOKEN_PREFIX = "tl_"


def token_sha256(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def _listed(scopes: str | Iterable[str]) -> list[str]:
    """The scope names given (comma-separated text or a list), stripped, blanks dropped."""
    items = [scope.strip() for scope in (scopes.split(",") if isinstance(scopes, str) else scopes)]
    return [scope for scope in items if scope]


def parse_scopes(scopes: str | Iterable[str]) -> list[str]:
    items = _listed(scopes)
    if not items:
        raise InputError(f"scopes: give at least one of {', '.join(SCOPES)}")
    unknown = [scope for scope in items if scope not in SCOPES]
    if unknown:
        raise InputError(f"scopes: {', '.join(unknown)} unknown; scopes are {', '.join(SCOPES)}")
    return [scope for scope in SCOPES if scope in items]


def granted(scopes: Iterable[str]) -> set[str]:
    out: set[str] = set()
    for scope in scopes:
        out |= IMPLIED.get(scope, set())
    return out


class NamedPerson(TypedDict):
    """A person as the audit trail and an approval's hashed content name them."""

    name: str
    function: str | None


@dataclass(frozen=True)
class Person:
    """The person behind a token: the name and function a certificate states for who approved or ran
    it."""

    name: str
    function: str | None = None

    def described(self) -> str:
        return f"{self.name}, {self.function}" if self.function else self.name


PERSON_TEXT_MAX = 200


def _check_person_text(what: str, key: str, value: object) -> None:
    """A person's name or function: printable text, not blank, at most PERSON_TEXT_MAX long."""
    if not isinstance(value, str) or not value.strip():
        need = (
            "the person's full name"
            if key == "name"
            else "their function in the laboratory, as text"
        )
        raise InputError(f"{what}.{key}: give {need}")
    if len(value) > PERSON_TEXT_MAX:
        raise InputError(f"{what}.{key}: longer than {PERSON_TEXT_MAX} characters")
    if any(ord(char) < 32 or 127 <= ord(char) < 160 for char in value):
        raise InputError(f"{what}.{key}: control characters are not allowed")


def person_of(fields: object, what: str = "person") -> Person:
    """A person from {"name", "function"}: a name of 1-200 printable characters, optionally a
    function as long."""
    if not isinstance(fields, dict):
        raise InputError(f'{what}: an object {{"name": ..., "function": ...}} is needed')
    unknown = sorted(set(fields) - {"name", "function"})
    if unknown:
        raise InputError(f"{what}.{unknown[0]}: unknown; a person has a name and a function")
    name, function = fields.get("name"), fields.get("function")
    for key, value, needed in (("name", name, True), ("function", function, False)):
        if value is None and not needed:
            continue
        _check_person_text(what, key, value)
    assert isinstance(name, str)
    return Person(name.strip(), function.strip() if isinstance(function, str) else None)


@dataclass(frozen=True)
class Principal:
    """Who a request is: the token's name, what it may do, and the person behind it (if the token
    names one)."""

    name: str
    scopes: frozenset[str]
    person: Person | None = None

    def may(self, scope: str) -> bool:
        return scope in self.scopes
