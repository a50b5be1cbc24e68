"""Fixtures of the fleet tests: a fresh PostgreSQL schema, and a proxy in front of the server a test
can cut."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import sqlalchemy as sa

from tests.helpers.fleet import postgres_schema_url
from tests.helpers.pg_proxy import PgProxy


@pytest.fixture
def database_url() -> Iterator[str]:
    with postgres_schema_url() as url:
        yield url


@pytest.fixture
def proxy(database_url: str) -> Iterator[PgProxy]:
    u = sa.make_url(database_url)
    p = PgProxy(u.host or "127.0.0.1", u.port or 5432)
    p.start()
    yield p
    p.stop()
