"""What every answer model shares."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class Answer(BaseModel):
    """A response body. Members beyond the declared ones are passed on, not dropped: clients ignore
    what they do not know, and an answer never loses a field it carries."""

    model_config = ConfigDict(extra="allow")
