"""The dashboard diagnoses a record and adopts it (headless Chromium, as test_dashboard_browser.py):
on a 180:1 / 360:1 bench with a worm periodic error, "Diagnose" follows the diagnosis to its end,
shows the named effect and the gap figures, and "Adopt as new version" makes the next version,
listed as made from it."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.helpers.benches import PERIODIC_X, scenario
from tests.helpers.browser import CHROMIUM, NEEDS_A_BROWSER, T, sync_playwright
from tests.helpers.diagnosis import BODY
from tests.helpers.running_service import running_service
from tests.helpers.waiting import eventually

if sync_playwright is not None:
    from playwright.sync_api import expect

pytestmark = NEEDS_A_BROWSER


@pytest.fixture(scope="module")
def daemon(tmp_path_factory) -> Iterator[tuple[str, dict[str, str]]]:
    data = tmp_path_factory.mktemp("data")
    path = data.parent / "periodic-bench.json"
    path.write_text(json.dumps(scenario("180-360", PERIODIC_X)))
    with running_service(data, TILTLAB_SIM_SPEED="5", TILTLAB_BENCH_SCENARIO=str(path)) as base:
        yield base, {"Authorization": f"Bearer {(data / 'admin.token').read_text().strip()}"}


def test_diagnose_from_the_dashboard_and_adopt(daemon):
    base, h = daemon
    r = httpx.post(f"{base}/calibrations", headers=h, json=BODY, timeout=30)
    assert r.status_code == 202, r.text
    job = eventually(
        lambda: httpx.get(f"{base}/calibrations/{r.json()['id']}", headers=h, timeout=30).json(),
        until=lambda job: job["state"] not in ("queued", "running"),
        timeout_s=600,
        every_s=0.5,
        what="the calibration ended",
    )
    assert job["state"] == "succeeded", job
    rec_id = job["record"]["id"]
    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"]
        )
        try:
            page = browser.new_page(bypass_csp=True, viewport={"width": 1280, "height": 900})
            page.goto(f"{base}/#token={h['Authorization'].split()[1]}")
            # the page knows its bench (its first answers are in) before it is used, as a person
            # sees the header before clicking
            expect(page.locator("body")).to_have_attribute("data-bench", "sim-stage", timeout=T)
            page.get_by_role("tab", name="Records").click()
            expect(page.locator("#view-records")).to_be_visible(timeout=T)
            page.locator(f"#records tr[data-id='{rec_id}']").click()
            expect(page.locator("#record-detail")).to_have_attribute(
                "data-id", str(rec_id), timeout=T
            )
            expect(page.locator("#diag-start")).to_be_enabled(timeout=T)
            page.click("#diag-start")
            expect(page.locator("#diag-state")).to_have_attribute(
                "data-state", "succeeded", timeout=10 * T
            )
            expect(page.locator("#diag-result")).to_contain_text("periodic_error")
            expect(page.locator("#diag-result")).to_contain_text("gap after")
            expect(page.locator("#diag-adopt")).to_be_visible()
            # the gap shrink drawn where people look: the diagnosis's residual maps side by side, on
            # one scale
            diag_id = int(page.locator("#diag-state").get_attribute("data-diagnosis") or 0)
            diagnosis = httpx.get(f"{base}/diagnoses/{diag_id}", headers=h, timeout=30).json()
            n = len(diagnosis["residual_maps"]["stage_deg"])
            for which in ("before", "after"):
                expect(page.locator(f"#diag-{which} g.res")).to_have_count(n, timeout=T)
            lengths = page.evaluate("""() => ['before', 'after'].map((w) => Math.max(...[...document.querySelectorAll(
                `#diag-${w} g.res line`)].map((l) => Math.hypot(l.x2.baseVal.value - l.x1.baseVal.value,
                                                              l.y2.baseVal.value - l.y1.baseVal.value))))""")
            assert lengths[1] < lengths[0], lengths  # the named effect shortens the arrows
            if os.environ.get("TILTLAB_SCREENSHOT_DIR"):
                page.evaluate("window.scrollTo(0, 0)")
                page.screenshot(
                    path=str(Path(os.environ["TILTLAB_SCREENSHOT_DIR"]) / "diagnosis.png"),
                    full_page=True,
                )
            expect(page.locator("#diag-adoption li[data-effect=periodic_error]")).to_have_attribute(
                "data-adoptable", "true"
            )
            page.click("#diag-adopt")
            expect(page.locator("#rec-msg")).to_contain_text("made from diagnosis", timeout=5 * T)
            records = httpx.get(f"{base}/records", headers=h, timeout=30).json()["records"]
            adopted = next(x for x in records if x["raw_data"].get("diagnosis_id"))
            assert "periodic_error" in adopted["raw_data"]["added_effects"]
            expect(page.locator("#record-detail")).to_have_attribute(
                "data-id", str(adopted["id"]), timeout=T
            )
            expect(page.locator(f"#records tr[data-id='{adopted['id']}']")).to_contain_text(
                "periodic_error"
            )
            # the new version is compared with the one it came from, over the grid both were
            # measured on
            grid = BODY["grid"]
            same = page.locator("#rec-compare [data-grids]")
            expect(same).to_have_attribute("data-grids", "same", timeout=T)
            expect(same).to_contain_text(f"{grid['n_x']} × {grid['n_y']} grid")
            # the new version links the diagnosis that made it; the diagnosis, shown on its record,
            # links the new one
            expect(page.locator("#rec-origin")).to_contain_text(
                f"made from diagnosis {diag_id} of record {rec_id}: periodic_error added"
            )
            page.click("#rec-origin-link")
            expect(page.locator("#record-detail")).to_have_attribute(
                "data-id", str(rec_id), timeout=T
            )
            expect(page.locator("#diag-state")).to_have_attribute(
                "data-diagnosis", str(diag_id), timeout=T
            )
            made = page.locator(f"#diag-made button[data-record='{adopted['id']}']")
            expect(made).to_be_visible(timeout=T)
            made.click()
            expect(page.locator("#record-detail")).to_have_attribute(
                "data-id", str(adopted["id"]), timeout=T
            )
        finally:
            browser.close()
