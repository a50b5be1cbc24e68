"""Shared dependencies of the routers: engine, store, benches and the job manager."""

from __future__ import annotations

from typing import Annotated

import sqlalchemy as sa
from fastapi import Depends, Query, Request

from service.api.problems import ProblemError
from service.bench.runtime import BenchRuntime
from service.storage.daemon_jobs import DaemonStore


def get_engine(request: Request) -> sa.Engine:
    return request.app.state.engine


def get_store(request: Request) -> DaemonStore:
    return request.app.state.store


def find_bench(request: Request, name: str | None, field: str = "bench") -> BenchRuntime:
    """The named bench, or the only one when the daemon runs one and no name is given."""
    benches: dict[str, BenchRuntime] = request.app.state.benches
    if name is None:
        if len(benches) == 1:
            return next(iter(benches.values()))
        raise ProblemError(422, "Bench not named", f"{field}: the daemon runs {len(benches)} benches"
                           f" ({', '.join(benches)}); name one", field=field)
    if name not in benches:
        raise ProblemError(404, "Unknown bench", f"{field}: no bench named {name!r}; benches: {', '.join(benches)}",
                           field=field)
    return benches[name]


async def bench_from_query(request: Request,
                     bench: Annotated[str | None, Query(description="bench name; may be left out when the daemon "
                                                        "runs a single bench")] = None) -> BenchRuntime:
    return find_bench(request, bench)


def get_jobs(request: Request):  # type: ignore[no-untyped-def]
    return request.app.state.jobs


EngineDep = Annotated[sa.Engine, Depends(get_engine)]
StoreDep = Annotated[DaemonStore, Depends(get_store)]
BenchQuery = Annotated[BenchRuntime, Depends(bench_from_query)]
