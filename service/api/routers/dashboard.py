"""The dashboard: the static page in web/, served at / with its ES modules and assets under /web,
and its icon at /favicon.ico (where browsers look for it)."""

from __future__ import annotations

from functools import cache
from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from service.resources import shipped_dir

router = APIRouter(tags=["dashboard"])


@cache
def web_dir() -> Path:
    return shipped_dir(
        "service.web",
        "web",
        lambda p: (p / "index.html").is_file() and (p / "js" / "main.js").is_file(),
    )


@router.get("/", include_in_schema=False)
def dashboard() -> FileResponse:
    return FileResponse(web_dir() / "index.html", media_type="text/html")


@router.get("/favicon.ico", include_in_schema=False)
def favicon() -> FileResponse:
    """The dashboard's icon (SVG: browsers take it whatever the name)."""
    return FileResponse(web_dir() / "favicon.svg", media_type="image/svg+xml")


def install(app: FastAPI) -> None:
    app.include_router(router)
    app.mount("/web", StaticFiles(directory=web_dir()), name="web")
