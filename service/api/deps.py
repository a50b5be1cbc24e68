"""Shared dependencies of the routers."""

from __future__ import annotations

from typing import Annotated

import sqlalchemy as sa
from fastapi import Depends, Request

from service.bench.simulated import SimulatedStageBench
from service.config import Settings


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_engine(request: Request) -> sa.Engine:
    return request.app.state.engine


def get_bench(request: Request) -> SimulatedStageBench:
    return request.app.state.bench


SettingsDep = Annotated[Settings, Depends(get_settings)]
EngineDep = Annotated[sa.Engine, Depends(get_engine)]
BenchDep = Annotated[SimulatedStageBench, Depends(get_bench)]
