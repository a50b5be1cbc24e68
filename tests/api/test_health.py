"""/health and /ready read the schema revision at most once per interval, off the event loop."""

from __future__ import annotations

import asyncio
import threading

import pytest
import sqlalchemy as sa
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.api.revision import SchemaRevision
from service.config import Settings
from service.storage.migrate import head_revision


def _engine(tmp_path, revision: str) -> sa.Engine:
    engine = sa.create_engine(f"sqlite:///{tmp_path / 'db.sqlite'}")
    with engine.begin() as c:
        c.execute(sa.text("CREATE TABLE alembic_version (version_num VARCHAR(32) NOT NULL)"))
        c.execute(sa.text("INSERT INTO alembic_version VALUES (:v)"), {"v": revision})
    return engine


def test_concurrent_requests_share_one_query_and_it_runs_off_the_loop(tmp_path, monkeypatch):
    engine = _engine(tmp_path, "0001")
    threads = []
    import service.api.revision as health

    real = health.current_revision

    def spy(e):  # type: ignore[no-untyped-def]
        threads.append(threading.current_thread())
        return real(e)

    monkeypatch.setattr(health, "current_revision", spy)

    async def go():  # type: ignore[no-untyped-def]
        rev = SchemaRevision(ttl_s=3600)
        got = await asyncio.gather(*(rev.get(engine) for _ in range(50)))
        return rev, got, threading.current_thread()

    rev, got, loop_thread = asyncio.run(go())
    assert got == ["0001"] * 50
    assert rev.queries == 1 and threads and all(t is not loop_thread for t in threads)


def test_a_changed_revision_is_seen_once_the_interval_is_over(tmp_path):
    engine = _engine(tmp_path, "0001")

    async def go():  # type: ignore[no-untyped-def]
        kept, fresh = SchemaRevision(ttl_s=3600), SchemaRevision(ttl_s=0)
        first = (await kept.get(engine), await fresh.get(engine))
        with engine.begin() as c:
            c.execute(sa.text("UPDATE alembic_version SET version_num = '0002'"))
        # the stale answer is served at once while one refresh runs; the next request sees the new
        # one
        served = await asyncio.gather(*(fresh.get(engine) for _ in range(20)))
        await fresh.refreshed()
        return first, served, (await kept.get(engine), await fresh.get(engine)), kept.queries, fresh

    first, served, second, kept_queries, fresh = asyncio.run(go())
    assert first == ("0001", "0001") and served == ["0001"] * 20
    assert second == ("0001", "0002") and kept_queries == 1 and fresh.queries >= 2


def test_a_failed_refresh_is_not_kept_and_the_next_request_sees_the_failure(tmp_path):
    engine = _engine(tmp_path, "0001")

    async def go():  # type: ignore[no-untyped-def]
        rev = SchemaRevision(ttl_s=0)
        assert await rev.get(engine) == "0001"
        with engine.begin() as c:
            c.execute(sa.text("DROP TABLE alembic_version"))
            c.execute(sa.text("CREATE TABLE alembic_version (other INTEGER)"))
        assert await rev.get(engine) == "0001"  # served while the refresh fails in the background
        await rev.refreshed()
        with pytest.raises(sa.exc.OperationalError):
            await rev.get(engine)

    asyncio.run(go())


def test_health_says_degraded_when_the_schema_is_not_at_head(tmp_path):
    with TestClient(create_app(Settings(data_dir=tmp_path))) as client:
        assert client.get("/health").json()["status"] == "ok"
        assert client.get("/ready").status_code in (200, 503)
        client.app.state.schema_revision = SchemaRevision(ttl_s=0)
        with client.app.state.engine.begin() as c:
            c.execute(sa.text("UPDATE alembic_version SET version_num = 'older'"))
        body = client.get("/health").json()
        assert body["status"] == "degraded" and body["schema_revision"] == "older"
        r = client.get("/ready")
        assert (
            r.status_code == 503
            and f"database schema at older, not {head_revision()}" in r.json()["reasons"]
        )
        with client.app.state.engine.begin() as c:
            c.execute(
                sa.text("UPDATE alembic_version SET version_num = :v"), {"v": head_revision()}
            )
