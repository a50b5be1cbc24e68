"""GET /benches and GET /devices: what the daemon runs and how each instrument is doing (from memory)."""

from __future__ import annotations

from fastapi import APIRouter, Request

from service.api.auth import Reader
from service.api.deps import BenchQuery

router = APIRouter(tags=["benches"])


@router.get("/benches")
def benches(request: Request, _: Reader) -> dict:
    """Every bench with its kind, roles and state (ready, busy, connecting, degraded) and who holds it."""
    node = request.app.state.settings.node
    fleet = request.app.state.fleet
    local = [{"name": b.name, "kind": b.kind, "roles": b.roles(), "state": b.state(),
              "held_by": None if b.holder is None else str(b.holder),
              "description": b.config.description, "simulated": _simulated(b), "node": node, "online": True}
             for b in request.app.state.benches.values()]
    return {"benches": local + (fleet.benches() if fleet is not None else [])}


@router.get("/devices")
def devices(bench: BenchQuery, _: Reader) -> dict:
    """Per device: role, port, protocol, state, last frame time, counters and identity."""
    out = []
    for st in bench.devices.status():
        c = st.counters
        ident = bench.identities.get(st.role) or st.identity
        out.append({"role": st.role, "port": st.port, "protocol": st.protocol, "state": st.state,
                    "last_frame_utc": st.last_frame_utc,
                    "counters": {"frames": c.frames, "bad_checksum": c.bad_checksum, "resyncs": c.resyncs,
                                 "timeouts": c.timeouts, "reconnects": c.reconnects},
                    "identity": None if ident is None else {"model": ident.model, "serial": ident.serial,
                                                            "firmware": ident.firmware},
                    "error": st.error})
    return {"bench": bench.name, "devices": out}


def _simulated(bench) -> dict | None:  # type: ignore[no-untyped-def]
    """For a simulated bench: its scenario(s) and speed-up; None on hardware."""
    if bench.sim is None:
        return None
    w = bench.sim.world
    names = [sc.name for sc in (getattr(w, "scenario", None), getattr(w, "rotation", None),
                                getattr(w, "turntable", None)) if sc is not None and hasattr(sc, "name")]
    return {"scenario": names[0] if names else None, "scenarios": names, "speed": bench.clock.speed}
