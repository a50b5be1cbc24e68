"""The tiltlab service: FastAPI application factory."""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager

from fastapi import FastAPI

from service import __version__
from service.api import problems
from service.api.routers import dashboard, health, tilt
from service.bench.simulated import SimulatedStageBench
from service.config import Settings, get_settings
from service.errors import InputError
from service.storage.engine import normalise_url
from service.storage.migrate import bootstrap

log = logging.getLogger("tiltlab")


def create_app(settings: Settings | None = None) -> FastAPI:
    """The application; an unusable database URL or bench scenario is refused here (InputError), before serving."""
    s = settings or get_settings()
    normalise_url(s.database_url)
    try:
        bench = SimulatedStageBench(s.bench_scenario)
    except InputError as exc:
        raise InputError(f"TILTLAB_BENCH_SCENARIO: {exc}") from exc

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        app.state.settings = s
        app.state.engine = bootstrap(s)  # brings the database to the current schema
        app.state.bench = bench
        log.info("tiltlab %s: database %s, bench %s", __version__, app.state.engine.url, app.state.bench.name)
        try:
            yield
        finally:
            app.state.engine.dispose()

    app = FastAPI(title="tiltlab", version=__version__, lifespan=lifespan,
                  description="Calibration, measurement and control of tilt with biaxial inclinometers.")
    problems.install(app)
    app.include_router(health.router)
    app.include_router(tilt.router)
    dashboard.install(app)
    return app
