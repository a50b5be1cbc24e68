"""A daemon on a simulated bench with the real drivers, sped up: in process, its instruments on
in-memory lines speaking the real bytes (tests/helpers/daemon.py)."""

from __future__ import annotations

import pytest

from tests.helpers.daemon import admin_headers, make_client


@pytest.fixture
def daemon(tmp_path):
    with make_client(tmp_path) as client:
        yield client, admin_headers(tmp_path)
