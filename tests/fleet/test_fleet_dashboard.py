"""The dashboard of one node shows the whole fleet: each bench with its node, the other node's bench
live, and a stopped node's bench as offline (headless Chromium, Playwright, Debian's chromium)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.helpers.fleet import Daemon, NatsServer, postgres_schema_url
from tests.helpers.running_service import free_port

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
try:
    from playwright.sync_api import expect, sync_playwright
except ImportError:  # pragma: no cover - playwright is a dev dependency
    sync_playwright = None  # type: ignore[assignment]

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.skipif(
        CHROMIUM is None,
        reason="needs Debian's chromium for browser tests (apt-get install chromium)",
    ),
    pytest.mark.skipif(
        sync_playwright is None, reason="needs playwright for Python (the dev dependencies)"
    ),
]
T = 30_000  # ms


def test_the_bench_selector_lists_the_fleet_and_streams_the_other_nodes_bench(
    tmp_path: Path,
) -> None:
    nats = NatsServer(tmp_path / "nats", free_port())
    nats.start()
    try:
        with postgres_schema_url() as db:
            common = {
                "TILTLAB_DATABASE_URL": db,
                "TILTLAB_BROKER_URL": nats.url,
                "TILTLAB_SIM_SPEED": "4",
                "TILTLAB_FLEET_LEASE_S": "3",
            }
            with Daemon(
                tmp_path / "a",
                {**common, "TILTLAB_NODE": "node-a", "TILTLAB_SIM_BENCH_NAME": "bench-a"},
            ) as a:
                token = (tmp_path / "a" / "admin.token").read_text().strip()
                b = Daemon(
                    tmp_path / "b",
                    {**common, "TILTLAB_NODE": "node-b", "TILTLAB_SIM_BENCH_NAME": "bench-b"},
                )
                with b, sync_playwright() as p:
                    browser = p.chromium.launch(
                        executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"]
                    )
                    page = browser.new_page(
                        bypass_csp=True, viewport={"width": 1280, "height": 900}
                    )
                    page.goto(f"{a.url}/#token={token}")
                    select = page.locator("#bench-select")
                    expect(select.locator("option[value=bench-a]")).to_have_text(
                        "bench-a · node-a", timeout=T
                    )
                    expect(select.locator("option[value=bench-b]")).to_have_text(
                        "bench-b · node-b", timeout=T
                    )
                    select.select_option("bench-b")  # node b's bench, live through node a
                    page.wait_for_function("window.tiltlab.live.received > 10", timeout=T)
                    page.get_by_role("tab", name="Status").click()
                    expect(page.locator("#benches tr[data-bench=bench-b]")).to_contain_text(
                        "node-b", timeout=T
                    )
                    b.__exit__(None, None, None)  # node b stops: its bench stays listed, offline
                    expect(page.locator("#benches tr[data-bench=bench-b]")).to_contain_text(
                        "node-b (offline)", timeout=T
                    )
                    expect(select.locator("option[value=bench-b]")).to_have_text(
                        "bench-b · node-b (offline)"
                    )
                    browser.close()
    finally:
        nats.stop()
