"""Scenarios: validated descriptions of simulated benches, and the presets that resemble the
papers."""

from service.scenarios.model import (
    Scenario,
    effects_dict,
    json_schema,
    load_scenario,
    parse_scenario,
    preset_names,
)
from service.scenarios.run import SimulatedRun, run_scenario

__all__ = [
    "Scenario",
    "SimulatedRun",
    "effects_dict",
    "json_schema",
    "load_scenario",
    "parse_scenario",
    "preset_names",
    "run_scenario",
]
