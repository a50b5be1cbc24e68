"""GET /benches and GET /devices: what the daemon runs and how each instrument is doing (from
memory)."""

from __future__ import annotations

from fastapi import APIRouter

from service.api.auth import Reader
from service.api.deps import BenchesDep, BenchQuery, FleetDep, SettingsDep
from service.api.models.benches import (
    Benches,
    BenchInfo,
    Counters,
    Devices,
    DeviceStatus,
    Identity,
    Simulated,
)
from service.api.models.problem import READ, problem_responses
from service.bench.runtime import BenchRuntime

router = APIRouter(tags=["benches"])


@router.get("/benches", response_model=Benches, responses=problem_responses(*READ))
def benches(all_benches: BenchesDep, settings: SettingsDep, fleet: FleetDep, _: Reader) -> Benches:
    """Every bench with its kind, roles and state (ready, busy, connecting, degraded) and who holds
    it."""
    local = [
        BenchInfo(
            name=bench.name,
            kind=bench.kind,
            roles=bench.roles(),
            state=bench.state(),
            held_by=None if bench.holder is None else str(bench.holder),
            description=bench.config.description,
            simulated=_simulated(bench),
            node=settings.node,
            online=True,
        )
        for bench in all_benches.values()
    ]
    remote = (
        [BenchInfo.model_validate(bench) for bench in fleet.benches()] if fleet is not None else []
    )
    return Benches(benches=local + remote)


@router.get("/devices", response_model=Devices, responses=problem_responses(*READ, 404))
def devices(bench: BenchQuery, _: Reader) -> Devices:
    """Per device: role, port, protocol, state, last frame time, counters and identity."""
    out = []
    for st in bench.devices.status():
        counters = st.counters
        ident = bench.identities.get(st.role) or st.identity
        out.append(
            DeviceStatus(
                role=st.role,
                port=st.port,
                protocol=st.protocol,
                state=st.state,
                last_frame_utc=st.last_frame_utc,
                counters=Counters(
                    frames=counters.frames,
                    bad_checksum=counters.bad_checksum,
                    resyncs=counters.resyncs,
                    timeouts=counters.timeouts,
                    reconnects=counters.reconnects,
                ),
                identity=None
                if ident is None
                else Identity(
                    model=ident.model,
                    serial=ident.serial,
                    firmware=ident.firmware,
                    address=ident.address,
                ),
                error=st.error,
            )
        )
    return Devices(bench=bench.name, devices=out)


def _simulated(bench: BenchRuntime) -> Simulated | None:
    """For a simulated bench: its scenario(s) and speed-up; None on hardware."""
    if bench.sim is None:
        return None
    world = bench.sim.world
    names = [
        scenario.name
        for scenario in (
            getattr(world, "scenario", None),
            getattr(world, "rotation", None),
            getattr(world, "turntable", None),
        )
        if scenario is not None and hasattr(scenario, "name")
    ]
    return Simulated(scenario=names[0] if names else None, scenarios=names, speed=bench.clock.speed)
