"""Scenarios: validated descriptions of simulated benches, and the presets that resemble the papers."""

from service.scenarios.model import (  # noqa: F401
    Scenario,
    effects_dict,
    json_schema,
    load_scenario,
    parse_scenario,
    preset_names,
)
from service.scenarios.run import SimulatedRun, run_scenario  # noqa: F401
