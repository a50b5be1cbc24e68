"""Simulated benches with hidden effects: the test bed of the discrepancy workflow.

A stacked-stage bench like seed 000's (its mounting and geometry effects drawn per seed
around the preset, coupling always on, its noise) with none, one or two candidate effects
of docs/models.md §5 switched on at a chosen multiple of the noise level. The workflow is
then asked to name what is hidden without being told.

Size of a hidden effect: the largest change it makes to a reading over the grid, once its
mean over the grid is removed (a constant is a zero offset, which every model has),
expressed as a multiple of the 1-sigma noise of one reading. For the periodic error, whose
sampled peak depends on its phase, the size is its amplitude.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from service.scenarios import parse_scenario, run_scenario
from service.scenarios.model import scenario_data

# hidden-effect variants: name -> (effect, parameter that carries it); "_y" variants act on the y
# axis
VARIANTS: dict[str, tuple[str, str]] = {
    "backlash": ("backlash", "x_deg"),
    "periodic_error": ("periodic_error", "x_amp_deg"),
    "periodic_error_y": ("periodic_error", "y_amp_deg"),
    "sensor_nonlinearity": ("sensor_nonlinearity", "{s}_x_per_deg"),
    "sensor_nonlinearity_y": ("sensor_nonlinearity", "{s}_y_per_deg"),
    "temperature_drift": ("temperature_drift", "{s}_x_deg_per_k"),
    "time_drift": ("time_drift", "{s}_x_deg_per_h"),
}

# Designs as the daemon's jobs record them (a point is a mean of readings): "grid10" today's 9 x 9
# job, 10 readings a point; "adaptive" the adaptive job at that job's U: its 4 x 4 spread of the
# +-12 deg lattice and, the total readings being about the same, 81 x 10 / 16 ~ 50 readings a point;
# "adaptive3" the same on a 3 x 3 spread (81 x 10 / 9 = 90 readings a point).
ADAPTIVE_DESIGNS: dict[str, tuple[tuple[float, ...], int]] = {
    "adaptive": ((-12.0, -3.0, 3.0, 12.0), 50),
    "adaptive3": ((-12.0, 0.0, 12.0), 90),
}
_MOUNTING = (
    "mounting_tilt",
    "sensor_yaw",
    "non_orthogonality",
    "axis_misalignment",
    "stage_scale",
    "zero_offset",
)
ENVIRONMENT = {"temp_c": 21.0, "temp_rate_c_per_h": 1.0, "temp_amp_c": 1.5, "temp_period_h": 0.5}


def base_scenario() -> dict:
    """The seed000 preset as a mutable dict, validated before anything is changed."""
    data, source = scenario_data("seed000")
    parse_scenario(data, source=source)
    return data


def noise_sigma_deg(sc: dict | None = None, sensor: str = "ref") -> float:
    """1-sigma noise of one reading: the sensor's white noise and the stage's repeatability
    together."""
    n = (sc or base_scenario())["effects"]["noise"]
    return float(np.hypot(n[f"{sensor}_sigma_deg"], n["stage_sigma_deg"]))


@dataclass
class HiddenBench:
    columns: dict
    hidden: dict[str, float]  # variant -> multiple of the noise
    params: dict  # the hidden effects' parameters as the scenario states them
    sigma_deg: float
    scenario: dict


def _effect_size(sc: dict, seed: int, sensor: str) -> np.ndarray:
    run = run_scenario(parse_scenario(sc), seed=seed, noiseless=True)
    return np.column_stack([run.columns[f"{sensor}_x_deg"], run.columns[f"{sensor}_y_deg"]])


def bench_with_hidden(
    seed: int,
    hidden: dict[str, float] | None = None,
    design: str = "serpentine",
    sensor: str = "ref",
    randomise_mounting: bool = True,
) -> HiddenBench:
    """Bench data with the given hidden variants, each at its multiple of the noise level."""
    hidden = dict(hidden or {})
    sc = base_scenario()
    sc["environment"] = dict(ENVIRONMENT)
    sc["grid"]["order"] = "random" if design == "random" else "serpentine"
    # an adaptive record at the fixed 9 x 9 job's U: its spread, each point a mean of readings
    if design in ADAPTIVE_DESIGNS:
        sc["grid"]["x_deg"] = sc["grid"]["y_deg"] = list(ADAPTIVE_DESIGNS[design][0])
    rng = np.random.default_rng(10_000 + seed)
    if randomise_mounting:
        for e in _MOUNTING:
            for k, v in list(sc["effects"].get(e, {}).items()):
                sc["effects"][e][k] = float(v * rng.uniform(0.5, 1.5) * rng.choice([-1.0, 1.0]))
    # sizes: multiples of one reading's noise, whatever the design
    sigma = noise_sigma_deg(sc, sensor)
    point_sigma = sigma
    readings = {**{k: v[1] for k, v in ADAPTIVE_DESIGNS.items()}, "grid10": 10}.get(design)
    # the sensor's noise averages over a point's readings, the stage's repeatability does not
    if readings:
        n = sc["effects"]["noise"]
        for s_ in ("ref", "meas"):
            n[f"{s_}_sigma_deg"] = n[f"{s_}_sigma_deg"] / np.sqrt(readings)
        point_sigma = noise_sigma_deg(sc, sensor)
    params: dict[str, dict[str, float]] = {}
    clean = copy.deepcopy(sc)
    clean["effects"].pop("noise", None)
    ref = _effect_size(clean, seed, sensor) if hidden else None
    for variant, mult in hidden.items():
        effect, par = VARIANTS[variant]
        par = par.format(s=sensor)
        target = mult * sigma
        if effect == "periodic_error":
            ax = par[0]
            value = target
            params.setdefault(effect, {})[f"{ax}_phase_deg"] = float(rng.uniform(-180.0, 180.0))
        else:
            probe = 1e-3 if effect != "sensor_nonlinearity" else 1e-4
            trial = copy.deepcopy(clean)
            trial["effects"].setdefault(effect, {})[par] = probe
            d = _effect_size(trial, seed, sensor) - ref
            peak = float(np.max(np.abs(d - d.mean(axis=0))))
            value = probe * target / peak
        params.setdefault(effect, {})[par] = float(value)
    for effect, ps in params.items():
        sc["effects"].setdefault(effect, {}).update(ps)
    run = run_scenario(parse_scenario(sc), seed=seed)
    return HiddenBench(run.columns, hidden, params, point_sigma, sc)
