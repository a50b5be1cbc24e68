"""/redoc refers to nothing outside the daemon: neither its page nor the script it loads names a
CDN."""

from __future__ import annotations

import re

from fastapi.testclient import TestClient

from service.api.app import create_app
from service.config import Settings


def test_redoc_page_and_its_scripts_fetch_nothing_remote(tmp_path) -> None:
    with TestClient(create_app(Settings(data_dir=tmp_path))) as client:
        page = client.get("/redoc")
        assert page.status_code == 200
        assets = re.findall(r'(?:src|href)="([^"]+)"', page.text)
        assert assets and all(a.startswith("/") for a in assets), assets
        for url in assets:
            r = client.get(url)
            assert r.status_code == 200, url
            if url.endswith(".js"):
                # images and scripts a bundle would load (src:"https://…"): none remote
                assert not re.search(r'src:"https?://', r.text), re.search(
                    r'.{80}src:"https?://.{60}', r.text
                )
                assert "cdn.redoc.ly" not in r.text
