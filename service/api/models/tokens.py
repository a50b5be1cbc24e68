"""Bodies of the token routes."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Literal

from pydantic import Field

from service.api.models.base import Answer
from service.jobs.requests import Line, RequestBody
from service.storage.tokens import SCOPES, TOKEN_NAME

Scope = Literal["read", "operate", "admin"]


class PersonIn(RequestBody):
    name: Annotated[
        Line,
        Field(
            min_length=1,
            max_length=200,
            examples=["Dr. Alice Example"],
            description="the person's full name, as certificates state who authorised them",
        ),
    ]
    function: (
        Annotated[
            Line,
            Field(
                min_length=1,
                max_length=200,
                examples=["Head of Laboratory"],
                description="their function in the laboratory (certificates state it; approving "
                "a record needs it)",
            ),
        ]
        | None
    ) = None


class Person(Answer):
    name: str
    function: str | None


class NewToken(RequestBody):
    name: Annotated[
        str,
        Field(
            pattern=f"^{TOKEN_NAME.pattern}$",
            description="1-100 letters, digits, '.', '_', '@' or '-', starting with a letter or "
            "digit; unique among active and revoked tokens",
            examples=["lims-reader"],
        ),
    ]
    scopes: Annotated[
        list[Scope],
        Field(
            min_length=1,
            max_length=len(SCOPES),
            description=f"some of {', '.join(SCOPES)}; admin implies operate, operate implies read",
            examples=[["read"]],
        ),
    ]
    person: PersonIn | None = Field(
        None,
        description="the person the token belongs to: who approves or runs "
        "calibrations with it (certificates name them)",
    )


class TokenPersonIn(RequestBody):
    person: PersonIn


class Token(Answer):
    name: str
    scopes: list[str]
    created_utc: dt.datetime
    created_by: str
    revoked_utc: dt.datetime | None
    person: Person | None = Field(
        None,
        description="the person behind the token; null for a token of a program "
        "(and for the first admin token until it is given one)",
    )


class CreatedToken(Token):
    token: str = Field(description="the token's text: in this answer only")


class Tokens(Answer):
    tokens: list[Token]
    next_cursor: int | None = Field(
        None, description="the `cursor` of the next page; null on the last page"
    )
