"""Bodies of the token routes."""

from __future__ import annotations

import datetime as dt
from typing import Annotated

from pydantic import Field

from service.api.models.base import Answer
from service.jobs.requests import RequestBody, Text
from service.storage.tokens import SCOPES


class NewToken(RequestBody):
    name: Annotated[Text, Field(description="1-100 letters, digits, '.', '_', '@' or '-', unique among active and "
                                            "revoked tokens", examples=["lims-reader"])]
    scopes: Annotated[list[Text], Field(min_length=1, max_length=len(SCOPES),
                                        description=f"some of {', '.join(SCOPES)}; admin implies operate, operate"
                                                    " implies read", examples=[["read"]])]


class Token(Answer):
    name: str
    scopes: list[str]
    created_utc: dt.datetime
    created_by: str
    revoked_utc: dt.datetime | None


class CreatedToken(Token):
    token: str = Field(description="the token's text: in this answer only")


class Tokens(Answer):
    tokens: list[Token]
