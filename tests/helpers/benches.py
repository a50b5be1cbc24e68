"""Benches other than seed 000's (the same mounting and noise, other stage hardware): their
scenarios and stage hardware, and the grid and hidden effect the bench tests use."""

from __future__ import annotations

import copy

import numpy as np

from service.physics.stage import StageBench
from service.scenarios import parse_scenario
from service.scenarios.model import scenario_data

# name -> hardware changes against the seed000 preset
BENCHES = {
    "seed000": {},
    "180-360": {"upper_gear_ratio": 180, "lower_gear_ratio": 360},
    "16-microsteps": {"microsteps": 16},
    "mirrored-y": {"meas_flip": "y"},
}
# 11 points over ±12 deg (2.4-deg steps): the worm phase is sampled at five phases on every bench
# above (a 3-deg grid samples a 180:1 worm at two phases only and a 360:1 worm at one)
GRID = {"start": -12, "stop": 12, "count": 11}
PERIODIC_X = {"periodic_error": {"x_amp_deg": 0.010, "x_phase_deg": 40.0}}


def scenario(bench: str, effects: dict | None = None, grid: dict | None = None) -> dict:
    data, _ = scenario_data("seed000")
    data = copy.deepcopy(data)
    data["bench"].update(BENCHES[bench])
    if grid is not None:
        data["grid"]["x_deg"] = dict(grid)
        data["grid"]["y_deg"] = dict(grid)
    for effect, params in (effects or {}).items():
        data["effects"].setdefault(effect, {}).update(params)
    parse_scenario(data)
    return data


def stage_bench(bench: str) -> StageBench:
    return StageBench(**{**StageBench().__dict__, **BENCHES[bench]})


def noise_sigma_deg(data: dict, sensor: str = "ref") -> float:
    n = data["effects"]["noise"]
    return float(np.hypot(n[f"{sensor}_sigma_deg"], n["stage_sigma_deg"]))
