"""Storage fixtures: a store on the database of `engine` (tests/conftest.py: SQLite and
PostgreSQL), and a device in it."""

from __future__ import annotations

import pytest
import sqlalchemy as sa

from service.storage.store import Store


@pytest.fixture
def store(engine: sa.Engine) -> Store:
    return Store(engine)


@pytest.fixture
def device(store: Store):  # type: ignore[no-untyped-def]
    return store.devices.add_device(
        "NS-25/E2",
        "SN1001",
        "dut",
        actor="alice",
        port="/dev/ttyUSB0",
        port_settings={"baud": 115200, "parity": "N"},
    )
