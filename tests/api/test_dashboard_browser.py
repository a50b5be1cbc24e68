"""The dashboard in headless Chromium (Playwright, Debian's chromium) against `tiltlab serve` on the simulated bench.

One daemon (sped up) and one browser serve the whole module; the tests run in file order: the live
chart, a lost and recovered stream, a calibration followed to its end and judged, levelling, the stop
button, and the page without a token. Screenshots of the main views go to TILTLAB_SCREENSHOT_DIR
(default: a pytest temporary folder).
"""

from __future__ import annotations

import datetime
import math
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.calibration.registry import methods_for
from tests.api.running_service import running_service

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
try:
    from playwright.sync_api import Browser, Page, expect, sync_playwright
except ImportError:  # pragma: no cover - playwright is a dev dependency
    sync_playwright = None  # type: ignore[assignment]

pytestmark = [
    pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium for browser tests (apt-get install chromium)"),
    pytest.mark.skipif(sync_playwright is None, reason="needs playwright for Python (the dev dependencies)"),
]

SIM_SPEED = "8"
GRID = {"x_min": "-1.5", "x_max": "1.5", "n_x": "3", "y_min": "-1.5", "y_max": "1.5", "n_y": "3"}
T = 30_000  # ms: how long a wait for something the page shows may take on a loaded machine


class Bench:
    def __init__(self, base: str, token: str, shots: Path, data: Path | None = None) -> None:
        self.base, self.token, self.shots, self.data = base, token, shots, data

    def get(self, path: str) -> dict:
        r = httpx.get(self.base + path, headers={"Authorization": f"Bearer {self.token}"}, timeout=30)
        r.raise_for_status()
        return r.json()

    def shot(self, page: Page, name: str) -> None:
        self.shots.mkdir(parents=True, exist_ok=True)
        page.evaluate("window.scrollTo(0, 0)")  # the sticky header at the top of a full-page picture
        page.screenshot(path=str(self.shots / f"{name}.png"), full_page=True)


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> Iterator[Bench]:
    data = tmp_path_factory.mktemp("data")
    shots = Path(os.environ.get("TILTLAB_SCREENSHOT_DIR") or tmp_path_factory.mktemp("screenshots"))
    with running_service(data, TILTLAB_SIM_SPEED=SIM_SPEED) as base:
        yield Bench(base, (data / "admin.token").read_text().strip(), shots, data)


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"])
        yield b
        b.close()


@pytest.fixture(scope="module")
def page(browser, bench) -> Iterator[Page]:
    """One signed-in page for the operator's tests (the session keeps the token)."""
    ctx = browser.new_context(viewport={"width": 1280, "height": 900}, accept_downloads=True)
    pg = ctx.new_page()
    pg.goto(f"{bench.base}/#token={bench.token}")
    yield pg
    ctx.close()


def readings_in_buffer(page: Page) -> int:
    return page.evaluate("window.tiltlab.ring.size")


def test_token_is_kept_for_the_session_and_leaves_the_address_bar(page, bench):
    expect(page.locator("#bench-select")).to_have_value("sim-stage", timeout=T)
    assert "token" not in page.url
    assert page.evaluate("sessionStorage.getItem('tiltlab-token')") == bench.token
    page.reload()  # the session still has it
    expect(page.locator("#bench-select")).to_have_value("sim-stage", timeout=T)
    expect(page.locator("#auth")).to_be_hidden()


def test_a_daemon_alone_names_its_benches_without_a_node(page, bench):
    expect(page.locator("#bench-select option[value=sim-stage]")).to_have_text("sim-stage", timeout=T)


def test_live_chart_receives_and_draws_readings(page, bench):
    page.wait_for_function("window.tiltlab.live.received > 50", timeout=T)
    # uPlot drew into both charts: its canvas, and the points the last redraw held
    expect(page.locator("#chart-tilt canvas")).to_have_count(1)
    expect(page.locator("#chart-raw canvas")).to_have_count(1)
    page.wait_for_function("Number(document.getElementById('chart-raw').dataset.points) > 50", timeout=T)
    # redraws are batched per animation frame: never more redraws than messages
    live = page.evaluate("({received: window.tiltlab.live.received, draws: window.tiltlab.live.draws})")
    assert 0 < live["draws"] <= live["received"] + 1, live
    # the numbers shown are the bench's, with their units
    ref_x = page.locator("#ref_x").inner_text()
    assert ref_x.endswith("°"), ref_x
    tilt = bench.get("/tilt")
    now = tilt["raw"]["reference_sensor"]["x_deg"]
    assert abs(float(ref_x.rstrip("°")) - now) < 0.05, (ref_x, now)
    temp = page.locator("#temp_c").inner_text()
    assert temp.endswith("°C") if tilt["temp_c"] is not None else temp == "—", (temp, tilt["temp_c"])
    # the window: ten seconds keeps what the chart draws within ten seconds of the newest reading
    page.select_option("#window", "10")
    page.wait_for_function("window.tiltlab.live.snapshots >= 2", timeout=T)
    page.wait_for_function("Number(document.getElementById('chart-raw').dataset.points) > 10", timeout=T)
    span = page.evaluate("""() => { const r = window.tiltlab.ring; const t = r.view(r.lastT - window.tiltlab.live.windowS).t;
                                    return t[t.length - 1] - t[0]; }""")
    assert 0 < span <= 10
    page.select_option("#window", "60")
    page.wait_for_function("window.tiltlab.live.snapshots >= 3", timeout=T)
    page.wait_for_function("Number(document.getElementById('chart-raw').dataset.points) > 50", timeout=T)
    bench.shot(page, "live")


def test_lost_stream_is_shown_and_recovered_with_the_gap_filled(page, bench):
    sockets = []
    blocked = {"on": False}

    def handler(ws):  # type: ignore[no-untyped-def]
        if blocked["on"]:
            ws.close(code=1011, reason="blocked by the test")
            return
        ws.connect_to_server()
        sockets.append(ws)

    page.route_web_socket("**/ws/readings**", handler)
    # reconnect so the stream goes through the route, then cut it and keep it cut for a while
    page.select_option("#rate", "10")
    page.wait_for_function("window.tiltlab.live.snapshots >= 4", timeout=T)
    assert sockets
    page.wait_for_function("window.tiltlab.live.received > 0", timeout=T)
    blocked["on"] = True
    t_lost = page.evaluate("window.tiltlab.ring.lastT")
    sockets[-1].close(code=1011, reason="connection cut by the test")
    banner = page.locator("#stream-banner")
    expect(banner).to_be_visible(timeout=T)
    expect(banner).to_contain_text("Live stream lost")
    expect(banner).to_contain_text("reconnecting in")
    page.wait_for_function("document.getElementById('stream-banner').textContent.includes('attempt 3')", timeout=T)
    bench.shot(page, "stream-lost")
    snapshots = page.evaluate("window.tiltlab.live.snapshots")
    blocked["on"] = False
    expect(banner).to_be_hidden(timeout=T)
    page.wait_for_function(f"window.tiltlab.live.snapshots > {snapshots}", timeout=T)
    # the reconnect snapshot's history filled the time the stream was cut
    filled = page.evaluate(f"""() => {{ const r = window.tiltlab.ring, t = r.view(0).t, t1 = window.tiltlab.live.snapshotT;
                                     let n = 0; for (const v of t) if (v > {t_lost} && v < t1) n++; return n; }}""")
    assert filled > 0
    page.unroute_all()


def test_calibration_followed_to_its_end_and_its_residual_map(page, bench):
    page.get_by_role("tab", name="Run").click()
    form = page.locator("#cal-form")
    for name, value in GRID.items():
        form.locator(f"input[name={name}]").fill(value)
    form.locator("input[name=samples_per_point]").fill("5")
    form.locator("input[name=n_validation]").fill("2")
    form.locator("input[name=settle_tolerance_deg]").fill("0.005")  # a loaded machine settles the simulation less evenly
    page.click("#cal-start")
    # the stop button is there while the job moves the stage
    expect(page.locator("#stop")).to_be_visible(timeout=T)
    page.wait_for_function("Number(document.getElementById('grid').dataset.measured) >= 2", timeout=T)
    bench.shot(page, "calibration-running")
    expect(page.locator("#job-state")).to_have_text("succeeded", timeout=180_000)
    job_id = int(page.locator("#job-id").inner_text().lstrip("#"))
    job = bench.get(f"/calibrations/{job_id}")
    assert job["state"] == "succeeded"
    # every measured point is on the picture of the grid
    expect(page.locator("#grid circle.measured")).to_have_count(job["progress"]["points_total"])
    expect(page.locator("#job-result")).to_contain_text("validation RMS")
    bench.shot(page, "calibration-done")

    page.click("#job-open-record")
    rec_id = job["record"]["id"]
    expect(page.locator("#record-detail")).to_have_attribute("data-id", str(rec_id), timeout=T)
    residuals = bench.get(f"/records/{rec_id}/residuals")
    for which in ("before", "after"):
        expect(page.locator(f"#res-{which} g.res")).to_have_count(len(residuals["points"]), timeout=T)
    assert page.locator("#res-rms-after").inner_text().endswith("″)")
    expect(page.locator("#rec-validation")).to_contain_text("RMS error")
    expect(page.locator("#rec-compare")).to_contain_text("first version")
    # the record's uncertainty budget: each contribution, then the combination
    expect(page.locator("#rec-budget")).to_contain_text("measurement sensor resolution")
    expect(page.locator("#rec-budget")).to_contain_text("combined: U =")
    expect(page.locator("#dl-cert")).to_be_disabled()  # a draft has no certificate
    with page.expect_download() as dl:
        page.click("#dl-model")
    assert dl.value.suggested_filename == f"record-{rec_id}-MODEL.json"
    assert Path(dl.value.path()).read_text().strip().startswith("{")
    with page.expect_download() as dl:
        page.click("#dl-points")
    assert Path(dl.value.path()).read_text().startswith("point,")
    page.click("#rec-activate")
    expect(page.locator("#rec-activate")).to_be_disabled(timeout=T)  # the record redrawn, now active
    expect(page.locator("#rec-msg")).to_contain_text(f"record {rec_id} is now active")  # and it still says so
    bench.shot(page, "record")


def test_live_card_names_a_record_activated_while_the_stream_is_open(page, bench):
    """The calibration test activated its record with the live stream open since before: the Live card
    names that record from the next reading on, with no new snapshot (no reload, no reconnect)."""
    active = bench.get("/tilt")["calibration"]
    assert active is not None, "the calibration test activates its record"
    snapshots = page.evaluate("window.tiltlab.live.snapshots")
    page.get_by_role("tab", name="Live").click()
    expect(page.locator("#calibration-note")).to_contain_text(f"record {active['record_id']} v{active['version']}",
                                                              timeout=T)
    assert page.evaluate("window.tiltlab.live.snapshots") == snapshots


def test_records_are_named_by_role_and_instrument(page, bench):
    page.get_by_role("tab", name="Records").click()
    rec = bench.get("/records?bench=sim-stage")["records"][0]
    ident = next(d["identity"] for d in bench.get("/devices")["devices"] if d["role"] == "measurement_sensor")
    cell = page.locator(f"#records tr[data-id='{rec['id']}'] td").nth(1)
    expect(cell).to_contain_text("measurement sensor", timeout=T)
    expect(cell).to_contain_text(ident["model"])
    assert "device" not in cell.inner_text()
    assert f"s/n {ident['serial']}" in (cell.get_attribute("title") or "")


def test_residual_maps_keep_arrows_in_the_frame_and_label_both_axes(page, bench):
    rec_id = bench.get("/tilt")["calibration"]["record_id"]
    page.get_by_role("tab", name="Records").click()
    page.locator(f"#records tr[data-id='{rec_id}']").click()
    expect(page.locator("#record-detail")).to_have_attribute("data-id", str(rec_id), timeout=T)
    n = len(bench.get(f"/records/{rec_id}/residuals")["points"])
    for which in ("before", "after"):
        svg = page.locator(f"#res-{which}")
        expect(svg.locator("g.res")).to_have_count(n, timeout=T)
        geo = svg.evaluate("""(svg) => {
            const box = (e) => { const b = e.getBBox(); return [b.x, b.y, b.x + b.width, b.y + b.height]; };
            return { frame: box(svg.querySelector("rect.frame")),
                     tips: [...svg.querySelectorAll("g.res line, g.res polygon")].map(box),
                     points: [...svg.querySelectorAll("g.res circle")].map(box),
                     longest: box(svg.querySelector(".longest")),
                     y: svg.querySelector(".y-label") && svg.querySelector(".y-label").textContent,
                     scale: svg.querySelectorAll(".colour-scale").length }; }""")
        fx0, fy0, fx1, fy1 = geo["frame"]
        for x0, y0, x1, y1 in geo["tips"]:  # every arrow, shaft and head, inside the frame
            assert fx0 <= x0 and x1 <= fx1 and fy0 <= y0 and y1 <= fy1, (which, geo["frame"], (x0, y0, x1, y1))
        lx0, ly0, lx1, ly1 = geo["longest"]  # the longest-arrow label covers no point
        for x0, y0, x1, y1 in geo["points"]:
            assert x1 < lx0 or lx1 < x0 or y1 < ly0 or ly1 < y0, (which, geo["longest"], (x0, y0, x1, y1))
        assert geo["y"] and "Y" in geo["y"], geo["y"]
        assert geo["scale"] == 1


def test_table_is_levelled(page, bench):
    assert bench.get("/tilt")["calibration"] is not None, "the calibration test activates its record"
    page.get_by_role("tab", name="Run").click()
    form = page.locator("#level-form")
    form.locator("input[name=x_deg]").fill("0.4")
    form.locator("input[name=y_deg]").fill("-0.3")
    form.locator("input[name=tolerance_deg]").fill("0.005")
    page.click("#level-go")
    expect(page.locator("#level-result")).to_have_attribute("data-within", "true", timeout=120_000)
    expect(page.locator("#level-result")).to_contain_text("within tolerance")
    t = bench.get("/tilt")["table_tilt"]
    assert abs(t["x_deg"] - 0.4) < 0.02 and abs(t["y_deg"] + 0.3) < 0.02, t
    page.get_by_role("tab", name="Live").click()
    page.wait_for_function("window.tiltlab.live.latest && window.tiltlab.live.latest.table_tilt", timeout=T)
    expect(page.locator("#tilt_x")).to_contain_text("±")
    bench.shot(page, "levelled")


def test_uncertainty_band_spans_the_reading_plus_minus_u(page, bench):
    """After levelling the table reads about (0.4, -0.3) deg: the band of each axis covers reading ± U
    on the chart's canvas, not the space between the reading and zero."""
    page.get_by_role("tab", name="Live").click()
    page.wait_for_function("window.tiltlab.live.latest && window.tiltlab.live.latest.table_tilt", timeout=T)
    page.wait_for_function("Number(document.getElementById('chart-tilt').dataset.points) > 20", timeout=T)
    got = page.evaluate("""() => {
        const u = window.tiltlab.charts.tilt, d = u.data, i = d[0].length - 3;
        const px = Math.round(u.valToPos(d[0][i], "x", true));
        const h = u.ctx.canvas.height, col = u.ctx.getImageData(px, 0, 1, h).data;
        const tinted = { x: [], y: [] };
        for (let r = 0; r < h; r++) {
            const [R, G, B, A] = col.slice(4 * r, 4 * r + 4);
            if (A > 0 && B > R + 60) tinted.x.push(r);
            if (A > 0 && R > B + 60) tinted.y.push(r);
        }
        const pos = (v) => u.valToPos(v, "y", true);
        return { tinted, x: [pos(d[4][i]), pos(d[3][i])], y: [pos(d[6][i]), pos(d[5][i])],
                 ux: (d[4][i] - d[3][i]) / 2, uy: (d[6][i] - d[5][i]) / 2, tx: d[1][i], ty: d[2][i] }; }""")
    tt = page.evaluate("window.tiltlab.live.latest.table_tilt")
    assert got["ux"] == pytest.approx(tt["u_x_deg"], rel=0.5) and got["uy"] == pytest.approx(tt["u_y_deg"], rel=0.5)
    assert abs(got["tx"]) > 0.2 and abs(got["ty"]) > 0.2, got  # far from zero against the band's width
    margin = 4  # canvas pixels: the line's width and anti-aliasing
    for axis in ("x", "y"):
        top, bottom = got[axis]
        rows = got["tinted"][axis]
        assert rows, (axis, got)
        outside = [r for r in rows if r < top - margin or r > bottom + margin]
        assert not outside, (axis, top, bottom, outside[:5], len(outside))
    bench.shot(page, "live-corrected")  # an active record: the corrected tilt with its band


def test_live_card_rounds_as_gum_and_keeps_each_label_with_its_value(page, bench):
    page.get_by_role("tab", name="Live").click()
    page.wait_for_function("window.tiltlab.live.latest && window.tiltlab.live.latest.table_tilt", timeout=T)
    for axis in ("x", "y"):
        text = page.locator(f"#tilt_{axis}").inner_text()
        m = re.fullmatch(r"(-?\d+(?:\.(\d+))?)° ± (\d+(?:\.(\d+))?)°", text)
        assert m, text
        value, u = float(m.group(1)), float(m.group(3))
        decimals = len(m.group(4) or "")
        assert len(m.group(2) or "") == decimals, text  # the value to the uncertainty's last digit
        digits = m.group(3).replace(".", "").lstrip("0")
        assert len(digits) == 2, text  # U to two significant digits
        assert u > 0 and 10 <= u * 10 ** decimals < 100, text
        tt = bench.get("/tilt")["table_tilt"]
        assert abs(value - tt[f"{axis}_deg"]) < 0.02 and math.isclose(u, tt[f"u_{axis}_deg"], rel_tol=0.1, abs_tol=10 ** -decimals), (text, tt)
        # the axis name stands on the line where its value begins, left of it
        label, first = page.locator(f"#tilt_{axis}").evaluate("""(o) => {
            const l = o.parentElement.querySelector('.axis-name') || o.previousElementSibling, a = l.getBoundingClientRect();
            const b = o.getClientRects()[0]; return [[a.left, a.top, a.right, a.bottom], [b.left, b.top, b.right, b.bottom]]; }""")
        assert label[2] <= first[0] + 1 and label[1] < first[3] and first[1] < label[3], (axis, label, first)
    note = page.locator("#calibration-note").inner_text()
    assert re.search(r"k = \d\.\d\d in X, k_y = \d\.\d\d in Y", note), note


@pytest.fixture(scope="module")
def real_time_bench(tmp_path_factory) -> Iterator[Bench]:
    """A bench whose stage moves at its real speed (2-3 deg/s), so a long move is still under way
    when the stop is clicked, however loaded the machine."""
    data = tmp_path_factory.mktemp("data-real-time")
    with running_service(data, TILTLAB_SIM_SPEED="1") as base:
        yield Bench(base, (data / "admin.token").read_text().strip(), Path(tmp_path_factory.mktemp("unused")))


def test_stop_button_stops_a_move(browser, real_time_bench):
    bench = real_time_bench
    ctx = browser.new_context(viewport={"width": 1280, "height": 900})
    page = ctx.new_page()
    page.goto(f"{bench.base}/#token={bench.token}")
    page.get_by_role("tab", name="Run").click()  # the tabs answer before the bench list has come
    form = page.locator("#move-form")
    expect(form).to_be_visible(timeout=T)
    expect(page.locator("body")).to_have_attribute("data-bench", "sim-stage", timeout=T)
    start = bench.get("/tilt")["stage"]
    target = -14.0 if (start["x_deg"] or 0.0) > 0 else 14.0
    form.locator("input[name=x_deg]").fill(str(target))
    form.locator("input[name=y_deg]").fill(str(target))
    page.click("#move-go")
    stop = page.locator("#stop")
    expect(stop).to_be_visible(timeout=T)
    stop.click()
    expect(stop).to_have_attribute("data-stopped", "1", timeout=T)
    expect(page.locator("#move-go")).to_be_enabled(timeout=T)  # the move's request came back
    # the stage stands short of the target
    page.wait_for_function("window.tiltlab.live.latest && !window.tiltlab.live.latest.stage.moving", timeout=T)
    stage = bench.get("/tilt")["stage"]
    assert not stage["moving"] and abs(stage["x_deg"] - target) > 0.5, (stage, target)
    expect(stop).to_be_hidden(timeout=T)
    ctx.close()


def test_controls_answer_while_the_bench_list_loads(browser, bench):
    """Held back /benches: a tab opens at once and a form sent says the list is still loading, sending nothing."""
    ctx = browser.new_context(viewport={"width": 1280, "height": 900})
    pg = ctx.new_page()
    held = []
    pg.route("**/benches", lambda route: held.append(route))
    sent = []
    pg.on("request", lambda req: sent.append(req.url) if "/stage/" in req.url else None)
    pg.goto(f"{bench.base}/#token={bench.token}")
    pg.wait_for_function("document.getElementById('bench-select') !== null")
    pg.get_by_role("tab", name="Run").click()
    expect(pg.locator("#move-form")).to_be_visible(timeout=T)
    pg.click("#move-go")
    expect(pg.locator("#move-result")).to_have_text("the bench list is still loading; send again in a moment", timeout=T)
    assert not sent, sent
    assert held, "the page asked for /benches"
    for route in held:
        route.continue_()
    expect(pg.locator("body")).to_have_attribute("data-bench", "sim-stage", timeout=T)
    ctx.close()


def test_status_view_shows_each_device(page, bench):
    page.get_by_role("tab", name="Status").click()
    devices = bench.get("/devices")["devices"]
    for d in devices:
        row = page.locator(f"#devices tr[data-role={d['role']}]")
        expect(row).to_contain_text(d["port"], timeout=T)
        expect(row).to_contain_text(d["state"])
    expect(page.locator("#devices tr[data-role=measurement_sensor]")).to_contain_text("record ")
    expect(page.locator("#benches")).to_contain_text("sim-stage")
    bench.shot(page, "status")


def test_devices_table_fits_its_box(page, bench):
    page.get_by_role("tab", name="Status").click()
    expect(page.locator("#devices tbody tr")).not_to_have_count(0, timeout=T)
    widths = page.locator("#devices").evaluate("(t) => [t.scrollWidth, t.parentElement.clientWidth]")
    assert widths[0] <= widths[1], widths


def test_status_view_makes_a_read_only_token_for_a_lims(page, bench):
    page.get_by_role("tab", name="Status").click()
    form = page.locator("#token-form")
    form.locator("input[name=name]").fill("lims-dashboard")
    form.locator("select[name=scope]").select_option("read")
    page.click("#token-make")
    shown = page.locator("#token-text")
    expect(shown).to_be_visible(timeout=T)
    token = shown.inner_text().strip()
    row = next(t for t in bench.get("/tokens")["tokens"] if t["name"] == "lims-dashboard")
    assert row["scopes"] == ["read"]
    h = {"Authorization": f"Bearer {token}"}
    assert httpx.get(bench.base + "/benches", headers=h, timeout=30).status_code == 200
    assert httpx.post(bench.base + "/stage/stop", headers=h, json={}, timeout=30).status_code == 403
    bench.shot(page, "token")


def test_run_tab_offers_only_methods_the_api_accepts(page, bench):
    offered = page.locator("#cal-form select[name=method] option").evaluate_all("(os) => os.map((o) => o.value)")
    assert offered
    accepted = methods_for("stage")
    assert set(offered) <= set(accepted), (offered, accepted)


def test_chart_time_axis_speaks_utc_in_any_browser_zone(browser, bench):
    ctx = browser.new_context(viewport={"width": 1280, "height": 900}, timezone_id="Asia/Kolkata")  # UTC+05:30
    pg = ctx.new_page()
    pg.goto(f"{bench.base}/#token={bench.token}")
    pg.wait_for_function("window.tiltlab.charts && Number(document.getElementById('chart-raw').dataset.points) > 20",
                         timeout=T)
    pg.wait_for_function("(window.tiltlab.charts.raw.axes[0]._values || []).length > 1", timeout=T)
    axis = pg.evaluate("(() => { const a = window.tiltlab.charts.raw.axes[0]; return [a._splits, a._values, a.label]; })()")
    splits, values, label = axis
    assert "UTC" in label
    for t, text in zip(splits, values, strict=True):
        if t is None or not text:
            continue
        utc = datetime.datetime.fromtimestamp(t, datetime.UTC).strftime("%H:%M:%S")
        assert text.startswith(utc), (t, text, utc)
    ctx.close()


def test_missing_and_invalid_tokens_get_a_clear_page(browser, bench):
    ctx = browser.new_context(viewport={"width": 820, "height": 1100})  # a tablet
    pg = ctx.new_page()
    pg.goto(f"{bench.base}/")
    expect(pg.locator("#auth")).to_be_visible(timeout=T)
    expect(pg.locator("#auth-title")).to_have_text("No access token")
    expect(pg.locator("header")).to_be_hidden()
    bench.shot(pg, "no-token")
    pg.goto(f"{bench.base}/#token=not-a-token")
    pg.reload()
    expect(pg.locator("#auth-title")).to_have_text("The token was not accepted", timeout=T)
    assert "401" in pg.locator("#auth-detail").inner_text()
    ctx.close()


def test_a_read_only_token_watches_and_is_told_what_it_lacks(browser, bench):
    """A token with the read scope alone sees the bench live; operating it says the operate scope is needed."""
    made = subprocess.run([sys.executable, "-m", "service", "token", "create", "--name", "viewer", "--scopes", "read"],
                          env={**os.environ, "TILTLAB_DATA_DIR": str(bench.data)}, capture_output=True, text=True,
                          timeout=60)
    assert made.returncode == 0, made.stderr
    viewer = made.stdout.strip()
    jobs_before = bench.get("/calibrations")["jobs"]
    ctx = browser.new_context(viewport={"width": 1280, "height": 900})
    pg = ctx.new_page()
    pg.goto(f"{bench.base}/#token={viewer}")
    pg.wait_for_function("window.tiltlab.live.received > 5", timeout=T)  # reading is allowed
    expect(pg.locator("#auth")).to_be_hidden()
    pg.get_by_role("tab", name="Run").click()
    pg.click("#cal-start")
    error = pg.locator("#cal-error")
    expect(error).to_be_visible(timeout=T)
    expect(error).to_contain_text("operate scope")
    assert bench.get("/calibrations")["jobs"] == jobs_before  # the refused request started nothing
    ctx.close()
