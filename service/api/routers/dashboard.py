"""The dashboard: the static page in web/, served at / with its assets under /web."""

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
    return shipped_dir("service.web", "web", lambda p: (p / "index.html").is_file() and (p / "dashboard.js").is_file())


@router.get("/", include_in_schema=False)
def dashboard() -> FileResponse:
    return FileResponse(web_dir() / "index.html", media_type="text/html")


def install(app: FastAPI) -> None:
    app.include_router(router)
    app.mount("/web", StaticFiles(directory=web_dir()), name="web")
