"""A simulated bench: the physics forward model of a scenario, driven like the real one.

It keeps the stage position and the time since start, and answers readings with the
scenario's noise, so the service behaves as it will on hardware.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from service.errors import InputError
from service.physics.stage import simulate_stage
from service.scenarios import load_scenario
from service.scenarios.model import StageScenario
from service.scenarios.run import effect_set, hardware_of


class SimulatedStageBench:
    def __init__(self, scenario_name: str = "seed000", seed: int | None = None):
        sc = load_scenario(scenario_name)
        if not isinstance(sc, StageScenario):
            raise InputError(f"scenario {scenario_name!r} is a {sc.kind} scenario; the service bench needs a stage one")
        self.scenario = sc
        self.bench = hardware_of(sc)
        self.effects = effect_set(sc)
        self._rng = np.random.default_rng(sc.seed if seed is None else seed)
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        self.stage_x_deg = 0.0
        self.stage_y_deg = 0.0
        self.dir_x = 1.0
        self.dir_y = 1.0

    @property
    def name(self) -> str:
        return f"simulated:{self.scenario.name}"

    def read(self) -> dict[str, float]:
        """One reading of both sensors at the current stage position."""
        with self._lock:
            t_s = time.monotonic() - self._t0
            env = self.scenario.environment
            out = simulate_stage(self.bench, self.effects, [self.stage_x_deg], [self.stage_y_deg], [self.dir_x],
                                 [self.dir_y], [env.temp_c], [t_s], rng=self._rng)
        return {"stage_x_deg": self.stage_x_deg, "stage_y_deg": self.stage_y_deg, "t_s": t_s, "temp_c": env.temp_c,
                **{k: float(out[k][0]) for k in ("ref_x_deg", "ref_y_deg", "meas_x_deg", "meas_y_deg")}}
