"""LIMS storage tests run on SQLite and PostgreSQL, with the storage tests' fixtures."""

from __future__ import annotations

import pytest

from service.storage.daemon_jobs import DaemonStore
from tests.storage.conftest import (  # noqa: F401 - fixtures
    backend,
    db_url,
    empty_engine,
    engine,
    postgres_schema_sql,
    sqlite_template,
)


@pytest.fixture
def lims(engine) -> DaemonStore:  # noqa: F811 - the engine fixture  # type: ignore[no-untyped-def]
    """The store the daemon uses: the lab's records, jobs, tokens and the LIMS tables."""
    return DaemonStore(engine)


@pytest.fixture(autouse=True)
def reviewed_certificates(monkeypatch):  # type: ignore[no-untyped-def]
    """Every certificate a LIMS test issues is checked as a reviewer would (tests/lims/reviewer.py)."""
    from service.lims import dcc
    from tests.lims.reviewer import problems

    issue = dcc.issue

    def reviewed(content):  # type: ignore[no-untyped-def]
        xml = issue(content)
        found = problems(xml)
        assert not found, found
        return xml

    monkeypatch.setattr(dcc, "issue", reviewed)
