"""/redoc with nothing fetched from outside: the package's ReDoc bundle is served from here with its
one remote asset (the "API docs by Redocly" logo from a CDN) pointed at a local image, so the page
makes no request beyond this daemon on an air-gapped lab network."""

from __future__ import annotations

import functools
from pathlib import Path

import fastapi_offline
from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html
from fastapi.responses import HTMLResponse, Response

REMOTE_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"
JS_URL = "/redoc-assets/redoc.standalone.js"


@functools.cache
def redoc_bundle(static_url: str) -> bytes:
    js = (Path(fastapi_offline.__file__).parent / "static" / "redoc.standalone.js").read_text(
        encoding="utf-8"
    )
    return js.replace(REMOTE_LOGO, f"{static_url}/favicon.png").encode("utf-8")


def install(app: FastAPI, static_url: str) -> None:
    """Replace the /redoc page of FastAPIOffline by one whose script refers to nothing remote."""
    app.router.routes = [
        route for route in app.router.routes if getattr(route, "path", None) != "/redoc"
    ]

    @app.get("/redoc", include_in_schema=False)
    async def redoc_html() -> HTMLResponse:
        return get_redoc_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title=f"{app.title} - ReDoc",
            redoc_js_url=JS_URL,
            redoc_favicon_url=f"{static_url}/favicon.png",
            with_google_fonts=False,
        )

    @app.get(JS_URL, include_in_schema=False)
    async def redoc_js() -> Response:
        return Response(
            redoc_bundle(static_url),
            media_type="text/javascript",
            headers={"Cache-Control": "public, max-age=86400"},
        )
