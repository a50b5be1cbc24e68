"""Simulated benches shared by the instrument tests: on an in-memory line, or on real
pseudo-terminals for the tests marked `pty`."""

from __future__ import annotations

import pytest

from service.clock import Clock
from service.instruments.sim import start_simulated_bench
from tests.helpers.instruments import SPEED


def _transport(request) -> str:
    """Pseudo-terminals where the test is about the pty (marked `pty`), else the in-memory line:
    the same drivers, port transport, reader thread, codecs and firmware, without the pty."""
    return "pty" if request.node.get_closest_marker("pty") else "loopback"


@pytest.fixture
def stage_sim(tmp_path, request):
    clock = Clock(SPEED)
    bench = start_simulated_bench(
        "seed000",
        "stage",
        clock,
        directory=tmp_path / "ports",
        adc=True,
        output_rate_hz=5,
        transport=_transport(request),
    )
    yield bench
    bench.close()


@pytest.fixture
def rotary_sim(tmp_path, request):
    clock = Clock(SPEED)
    bench = start_simulated_bench(
        "seed002-sim",
        "rotary",
        clock,
        directory=tmp_path / "ports",
        output_rate_hz=5,
        transport=_transport(request),
    )
    yield bench
    bench.close()
