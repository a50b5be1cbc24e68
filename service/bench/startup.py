"""Which benches the daemon runs: those of a bench configuration (real ports), or by default a
simulated stage bench on pseudo-terminals, reached through the same drivers as hardware."""

from __future__ import annotations

from typing import Any, Literal

from service.bench.runtime import BenchRuntime
from service.clock import Clock
from service.config import Settings
from service.errors import InputError
from service.instruments.bench_config import load_bench_config


def check_sim_speed(settings: Settings) -> None:
    """A speed-up the simulated lines cannot carry is refused before anything starts (the frames
    would queue without end, the readings arrive ever later and requests time out)."""
    if settings.bench_config is not None:
        return
    from service.instruments.sim import fastest_speed

    for kind in settings.sim_benches:
        limit, why = fastest_speed(kind)
        if settings.sim_speed > limit:
            raise InputError(
                f"TILTLAB_SIM_SPEED (--sim-speed) {settings.sim_speed:g} is more than the "
                f"simulated {kind} bench can run: {why}, so at most {limit:g} times real time"
            )


def plan_benches(settings: Settings) -> list[BenchRuntime]:
    """Open (but not start) every bench; an unusable configuration is an InputError naming it."""
    if settings.bench_config is not None:
        benches_file = load_bench_config(settings.bench_config)
        speed = benches_file.sim_speed or settings.sim_speed
        clock = Clock(speed)
        return [BenchRuntime(cfg, clock) for cfg in benches_file.benches.values()]
    clock = Clock(settings.sim_speed)
    runtimes: list[Any] = []
    for kind in settings.sim_benches:
        runtimes.append(_simulated_runtime(settings, kind, clock, runtimes))
    return runtimes


def _simulated_runtime(
    settings: Settings, kind: Literal["stage", "rotary"], clock: Clock, started: list[Any]
) -> BenchRuntime:
    """A simulated bench of `kind` on its scenario; a scenario refused closes the benches `started`
    so far and is named by its setting."""
    from service.instruments.sim import start_simulated_bench

    scenario = settings.bench_scenario if kind == "stage" else settings.rotary_scenario
    try:
        sim = start_simulated_bench(
            scenario,
            kind,
            clock,
            adc=(kind == "stage"),
            transport=settings.sim_transport,
            ambient=settings.sim_ambient_sensor,
        )
    except InputError as exc:
        var = "TILTLAB_BENCH_SCENARIO" if kind == "stage" else "TILTLAB_ROTARY_SCENARIO"
        for runtime in started:
            runtime.sim.close()
        raise InputError(f"{var}: {exc}") from exc
    config = sim.config
    if kind == "stage" and settings.sim_bench_name:
        config = config.model_copy(update={"name": settings.sim_bench_name})
    return BenchRuntime(config, clock, sim=sim)
