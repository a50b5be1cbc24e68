"""Bodies of /health and /ready."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from service.api.models.base import Answer


class Health(Answer):
    status: Literal["ok", "degraded"] = Field(description="degraded when the database schema is not at head")
    version: str
    database: str = Field(description="the database URL without its password")
    schema_revision: str | None
    bench: str = Field(description="the bench, or the benches joined by commas")
    benches: list[str]


class Readiness(Answer):
    ready: bool
    reasons: list[str] = Field(description="why not ready, one line each")
