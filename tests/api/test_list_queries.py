"""Routes that list things read them in a few batched queries, however many rows a page holds: a
page of many jobs or records costs the same number of statements as a page of a few (no query per
row)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import pytest
import sqlalchemy as sa
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.api import problems
from service.api.routers import calibrations, lims, records
from service.config import Settings
from service.jobs.manager import JobManager
from service.storage.store import Store

# per listing request, whatever the page size (a session's own statements included)
MAX_STATEMENTS = 10


@contextmanager
def counted(bind: sa.Engine) -> Iterator[list[str]]:
    """The SQL statements the engine runs inside the block."""
    seen: list[str] = []

    def count(conn, cursor, statement, parameters, context, executemany):  # type: ignore[no-untyped-def]
        seen.append(statement)

    sa.event.listen(bind, "before_cursor_execute", count)
    try:
        yield seen
    finally:
        sa.event.remove(bind, "before_cursor_execute", count)


def add_measured_jobs(store: Store, device_id: int, n: int, order_id: int) -> None:
    """Jobs that each made a record, half of them approved (statuses to read as well)."""
    for _ in range(n):
        job = store.jobs.create_job(device_id, "scale", "linear", actor="olga", order_id=order_id)
        store.jobs.start_job(job.id, actor="olga")
        record = store.records.add_record(
            device_id, "scale", "linear", {"parameters": {}}, operator="olga", job_id=job.id
        )
        store.jobs.succeed_job(job.id, actor="olga")
        if record.version % 2:
            store.approvals.decide(
                record.id, decision="approve", meaning="approval", note="", actor="rita"
            )


@pytest.fixture
def listed(engine: sa.Engine, tmp_path) -> Iterator[tuple[Store, TestClient, int, int]]:  # type: ignore[no-untyped-def]
    store = Store(engine)
    device = store.devices.add_device("SCA126T", "SN-1", "measurement_sensor", actor="setup")
    order, _ = store.orders.create_order(
        {
            "lims_order_id": "LIMS-1",
            "item_serial": "SN-1",
            "procedure": "scale",
            "method": "linear",
            "customer": {"name": "Survey Ltd", "city": "Berlin", "country_code": "DE"},
        },
        actor="setup",
    )
    app = FastAPI()
    problems.install(app)
    for module in (calibrations, records, lims):
        app.include_router(module.router)
    app.state.settings = Settings(data_dir=tmp_path, auth="none")
    app.state.store, app.state.benches = store, {}
    app.state.jobs = JobManager(store, app.state.benches)
    with TestClient(app) as client:
        yield store, client, device.id, order.id


def test_a_page_of_many_jobs_records_or_order_links_costs_the_statements_of_a_few(listed) -> None:  # type: ignore[no-untyped-def]
    store, client, device_id, order_id = listed
    routes = (
        "/calibrations?limit=500",
        "/records",
        f"/records?device={device_id}",
        f"/orders/{order_id}",
    )
    statements: dict[int, dict[str, int]] = {}
    made = 0
    for total in (3, 40):
        add_measured_jobs(store, device_id, total - made, order_id)
        made = total
        statements[total] = {}
        for route in routes:
            with counted(store.engine) as seen:
                answer = client.get(route)
            assert answer.status_code == 200, answer.text
            statements[total][route] = len(seen)
    assert len(client.get("/calibrations?limit=500").json()["jobs"]) == 40
    assert len(client.get("/records").json()["records"]) == 40
    assert statements[40] == statements[3], statements
    assert max(statements[40].values()) <= MAX_STATEMENTS, statements
