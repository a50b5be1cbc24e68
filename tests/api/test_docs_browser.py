"""/docs and /redoc render the API in a real headless browser with no network but the service's:
their scripts and styles come from the installed package, not from a CDN."""

from __future__ import annotations

import subprocess
from pathlib import Path

import httpx
import pytest

from tests.helpers.browser import CHROMIUM
from tests.helpers.running_service import running_service

pytestmark = pytest.mark.skipif(
    CHROMIUM is None,
    reason="needs Debian's chromium for browser tests (apt-get install chromium; .ci/run installs "
    "it)",
)

# Every host name fails to resolve except the service's own address: an air-gapped lab network.
OFFLINE = "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE 127.0.0.1"


def offline_dom(url: str, profile: Path) -> str:
    args = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        OFFLINE,
        f"--user-data-dir={profile}",
        "--window-size=1200,800",
        "--virtual-time-budget=10000",
        "--dump-dom",
        url,
    ]
    r = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


def test_docs_and_redoc_render_without_network(tmp_path: Path) -> None:
    with running_service(tmp_path / "data") as base:
        for page in ("docs", "redoc"):
            html = httpx.get(f"{base}/{page}", timeout=5).text
            assert "cdn." not in html and "https://" not in html.split("<body", 1)[1], page
        swagger = offline_dom(f"{base}/docs", tmp_path / "profile-docs")
        redoc = offline_dom(f"{base}/redoc", tmp_path / "profile-redoc")
    # Swagger UI drew one operation block per route, from the service's own OpenAPI document
    assert swagger.count('class="opblock opblock-get') >= 2, swagger[-2000:]
    assert "/health" in swagger and "/tilt" in swagger
    # ReDoc drew the API's title and its operations
    assert "Download OpenAPI specification" in redoc, redoc[-2000:]
    assert "/health" in redoc and "/tilt" in redoc
