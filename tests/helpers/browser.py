"""Headless Chromium for the browser tests (Playwright driving Debian's chromium): where it is, the
marks that skip a module without it, and how long a wait on the page may take."""

from __future__ import annotations

import shutil

import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
try:
    from playwright.sync_api import expect, sync_playwright
except ImportError:  # pragma: no cover - playwright is a dev dependency
    expect = None  # type: ignore[assignment]
    sync_playwright = None  # type: ignore[assignment]

# a module's `pytestmark`: skipped without the browser or without playwright
NEEDS_A_BROWSER = [
    pytest.mark.skipif(
        CHROMIUM is None,
        reason="needs Debian's chromium for browser tests (apt-get install chromium)",
    ),
    pytest.mark.skipif(
        sync_playwright is None, reason="needs playwright for Python (the dev dependencies)"
    ),
]

T = 30_000  # ms: how long a wait for something the page shows may take on a loaded machine
if expect is not None:  # every `expect` without a timeout of its own waits as long (not 5 s)
    expect.set_options(timeout=T)
