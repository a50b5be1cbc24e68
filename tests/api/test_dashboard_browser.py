"""The dashboard in a real headless browser (Debian's chromium), against a real server.

Chromium loads the page, runs its script for a few seconds of virtual time and prints the
DOM it then holds; the tests read what a person would see from that DOM.
"""

from __future__ import annotations

import functools
import http.server
import json
import re
import shutil
import subprocess
import threading
from html.parser import HTMLParser
from pathlib import Path

import httpx
import pytest

from service.api.routers.dashboard import web_dir
from tests.api.running_service import running_service

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="needs Debian's chromium for browser tests (apt-get install chromium; .ci/run installs it)")

NUMBER = re.compile(r"^-?\d+\.\d{4}$")


def browse(url: str, profile: Path, *, virtual_ms: int = 6000, screenshot: Path | None = None) -> str:
    """The DOM after the page has run for virtual_ms of virtual time (or a screenshot of it)."""
    args = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            f"--user-data-dir={profile}", "--window-size=1200,800", f"--virtual-time-budget={virtual_ms}"]
    args += [f"--screenshot={screenshot}"] if screenshot else ["--dump-dom"]
    r = subprocess.run([*args, url], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


_VOID = ("circle", "line", "link", "meta", "polyline")  # no text inside; self-closed or void in the dumped DOM


class _TextById(HTMLParser):
    """Text content and attributes of every element that has an id."""

    def __init__(self) -> None:
        super().__init__()
        self.text: dict[str, str] = {}
        self.attrs: dict[str, dict[str, str | None]] = {}
        self._open: list[str | None] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag in _VOID:
            if "id" in a:
                self.attrs[a["id"]] = a
            return
        self._open.append(a.get("id"))
        if a.get("id"):
            self.attrs[a["id"]] = a
            self.text.setdefault(a["id"], "")

    def handle_endtag(self, tag):
        if tag not in _VOID and self._open:
            self._open.pop()

    def handle_data(self, data):
        for ident in self._open:
            if ident:
                self.text[ident] += data


def seen(dom: str) -> _TextById:
    p = _TextById()
    p.feed(dom)
    return p


def test_dashboard_shows_the_live_bench(tmp_path):
    with running_service(tmp_path / "data") as base:
        token = (tmp_path / "data" / "admin.token").read_text().strip()
        page = seen(browse(f"{base}/#token={token}", tmp_path / "profile"))
        t = httpx.get(f"{base}/tilt", timeout=5, headers={"Authorization": f"Bearer {token}"}).json()
    now = {"ref_x_deg": t["raw"]["reference_sensor"]["x_deg"], "ref_y_deg": t["raw"]["reference_sensor"]["y_deg"],
           "meas_x_deg": t["raw"]["measurement_sensor"]["x_deg"], "meas_y_deg": t["raw"]["measurement_sensor"]["y_deg"],
           "stage_x_deg": t["stage"]["x_deg"], "stage_y_deg": t["stage"]["y_deg"]}

    assert page.text["bench"] == "sim-stage" and page.text["schema"].strip()
    assert "banner" in page.attrs and "hidden" in page.attrs["banner"], page.text.get("banner")
    for k in ("ref_x_deg", "ref_y_deg", "meas_x_deg", "meas_y_deg", "stage_x_deg", "stage_y_deg"):
        assert NUMBER.match(page.text[k].strip()), (k, page.text[k])
        # the readings are noisy (a few thousandths of a degree), the mounting errors they show are not
        assert abs(float(page.text[k]) - now[k]) < 0.02, (k, page.text[k], now[k])
    # no active calibration: the tilt is not invented, and the page says why
    assert page.text["tilt_x_deg"].strip() == "—" and "no active calibration" in page.text["note"]
    # it keeps polling: several readings in the trace, one point per reading on each axis
    count = int(page.text["trace_count"])
    assert count >= 2
    for axis in ("trace-x", "trace-y"):
        assert len(page.attrs[axis]["points"].split()) == count
    # the level's dots sit where the reference reading says, on its scale
    scale = float(page.text["level_range_deg"])
    assert float(page.attrs["dot-ref"]["cx"]) == pytest.approx(100 * float(page.text["ref_x_deg"]) / scale, abs=0.05)
    assert float(page.attrs["dot-ref"]["cy"]) == pytest.approx(-100 * float(page.text["ref_y_deg"]) / scale, abs=0.05)


class _PageOnlyHandler(http.server.SimpleHTTPRequestHandler):
    """Serves the dashboard's files like the service, but every API call fails as a broken service would."""

    def do_GET(self):  # noqa: N802 (http.server's name)
        if self.path == "/" or self.path.startswith("/web/"):
            self.path = "/index.html" if self.path == "/" else self.path[len("/web"):]
            return super().do_GET()
        body = json.dumps({"type": "about:blank", "title": "Service Unavailable", "status": 503,
                           "detail": "bench not connected"}).encode()
        self.send_response(503)
        self.send_header("Content-Type", "application/problem+json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


def test_dashboard_says_what_failed_when_the_service_answers_with_a_problem(tmp_path):
    handler = functools.partial(_PageOnlyHandler, directory=str(web_dir()))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        page = seen(browse(f"http://127.0.0.1:{server.server_address[1]}/", tmp_path / "profile", virtual_ms=4000))
    finally:
        server.shutdown()
    assert "hidden" not in page.attrs["banner"]
    assert re.search(r"/(tilt|health) answered HTTP 503: bench not connected", page.text["banner"]), page.text["banner"]
    assert page.text["ref_x_deg"].strip() == "—"  # nothing shown that was not read
