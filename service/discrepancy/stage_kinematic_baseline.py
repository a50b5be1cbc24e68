"""The `kinematic` baseline of a stage bench: the physical forward model without the candidate
effects.

The model is the simulator itself (service.physics.stage, through the stage-effect fitter's
`StageEffectModel`), with the mounting and geometry parameters free; a candidate adds its own
effect's parameters, in the registry's names and units, to the free set. So "add the
effect" means literally switching the simulator's term on and fitting its size.

The free geometry is the largest set the readings of one sensor can separate (pivoted QR of
the model's Jacobian on a 9 × 9 grid): the sensor's zero offsets, both stage scales, the
sensor's yaw and non-orthogonality, the desk tilt seen by y readings and the sensor seat's
tilt seen by x readings, and three axis-misalignment angles. The other geometry parameters
are exact symmetries of these on stage data (a yaw of the lower axis, the table top against
the seat, ...) and are left at zero; the sensor's own scale factor is represented by the
stage scale to first order (they differ only through the off-axis coupling).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from service.calibration.stage_effect_fit import StageEffectModel, StagePoints, typical_scale
from service.discrepancy.model import Block, Family, Fit
from service.discrepancy.report_types import Magnitude, ReportExtra
from service.discrepancy.stage_data import (
    STAGE_SEPARABILITY_HINTS,
    StageData,
    candidate_block,
    sensor_param_names,
)
from service.discrepancy.stage_linear_baseline import stage_magnitude
from service.errors import InputError
from service.physics.effects import STAGE_EFFECTS
from service.physics.stage import StageGeometry, simulate_stage

CANDIDATES = (
    "backlash",
    "periodic_error",
    "sensor_nonlinearity",
    "temperature_drift",
    "time_drift",
)

ALREADY_IN_MODEL = {
    "offaxis_coupling": "the kinematic model is the stacked-stage geometry itself: the coupling is "
    "built in",
    "zero_offset": "the sensor's zero offsets are free parameters of the baseline",
    "scale_factor": "the stage scales are free; a sensor gain differs from them only through "
    "the coupling (second order), so it is represented to first order",
    "sensor_yaw": "free parameter of the baseline",
    "non_orthogonality": "free parameter of the baseline",
    "mounting_tilt": "desk tilt (y) and sensor-seat tilt (x) are free; the other plane tilts "
    "are exact symmetries of these on one sensor's readings",
    "axis_misalignment": "lower-axis pitch, upper-axis pitch and perpendicularity are free; the "
    "lower axis' yaw is an exact symmetry of the sensor yaw on these readings",
    "stage_scale": "free parameter of the baseline (both stages)",
}


def geometry_params(s: str) -> tuple[tuple[str, str], ...]:
    return (
        ("zero_offset", f"{s}_x_deg"),
        ("zero_offset", f"{s}_y_deg"),
        ("stage_scale", "x"),
        ("stage_scale", "y"),
        ("sensor_yaw", f"{s}_deg"),
        ("non_orthogonality", f"{s}_deg"),
        ("mounting_tilt", "desk_y_deg"),
        ("mounting_tilt", f"{s}_x_deg"),
        ("axis_misalignment", "upper_pitch_deg"),
        ("axis_misalignment", "perpendicularity_deg"),
        ("axis_misalignment", "lower_pitch_deg"),
    )


_GEOMETRY_EFFECTS = {
    "mounting_tilt",
    "axis_misalignment",
    "sensor_yaw",
    "non_orthogonality",
    "offaxis_coupling",
}


def detect_flip(data: StageData) -> str:
    """How the sensor is mounted (docs/models.md §2: the measurement sensor may be upside down),
    from the slopes."""
    if data.sensor != "meas":
        return "none"
    sx = (
        np.polyfit(data.cmd_x_deg, data.observed[:, 0], 1)[0] if np.ptp(data.cmd_x_deg) > 0 else 1.0
    )
    sy = (
        np.polyfit(data.cmd_y_deg, data.observed[:, 1], 1)[0] if np.ptp(data.cmd_y_deg) > 0 else 1.0
    )
    if sx < 0 and sy < 0:
        raise InputError(
            "both measurement-sensor axes read against their stages: the kinematic model "
            "supports a sensor turned over about one of its axes, not one turned half round "
            "(use --baseline linear)"
        )
    return "y" if sx < 0 else ("x" if sy < 0 else "none")


class StageKinematic(Family):
    kind = "stage"
    baseline = "kinematic"
    unit = "deg"
    axes = ("x", "y")
    candidates = CANDIDATES
    already_in_model = ALREADY_IN_MODEL
    separability_hints = STAGE_SEPARABILITY_HINTS

    def __init__(self, data: StageData, weights: NDArray[np.float64]):
        super().__init__(data.observed, weights)
        self.data = data
        bench = data.bench
        flip = detect_flip(data)
        temp_ref = float(np.mean(data.temp_c)) if data.temp_c is not None else bench.temp_ref_c
        self.bench = dataclasses.replace(
            bench, travel_deg=max(bench.travel_deg, 90.0), meas_flip=flip, temp_ref_c=temp_ref
        )
        cols = {"stage_x_deg": data.cmd_x_deg, "stage_y_deg": data.cmd_y_deg}
        for column in ("dir_x", "dir_y", "temp_c"):
            values = getattr(data, column)
            if values is not None:
                cols[column] = values
        if data.t_s is not None:
            cols["t_s"] = data.t_s - float(data.t_s[0])
        self.pts = StagePoints.from_columns(cols)
        self.outputs = [f"{data.sensor}_x_deg", f"{data.sensor}_y_deg"]
        self.geometry_keys = geometry_params(data.sensor)
        self.names = sensor_param_names(data.sensor)
        self._geo_cache: tuple[tuple[object, ...], StageGeometry] | None = None
        self.report_extra: ReportExtra = {
            "kinematic": {
                "meas_flip": flip,
                "temp_ref_c": temp_ref,
                "free_geometry": [f"{effect}.{param}" for effect, param in self.geometry_keys],
            }
        }

    def full_blocks(self, effects: tuple[str, ...]) -> list[Block]:
        keys = self.geometry_keys
        out = [
            Block(
                "baseline",
                tuple(f"{effect}.{param}" for effect, param in keys),
                tuple(STAGE_EFFECTS[effect].param(param).unit for effect, param in keys),
                tuple(typical_scale(k) for k in keys),
                (0.0,) * len(keys),
            )
        ]
        for effect in effects:
            if (block := candidate_block(effect, self.names)) is not None:
                out.append(block)
            else:
                raise KeyError(f"the kinematic baseline has no candidate term for {effect!r}")
        return out

    def effects_mapping(
        self, effects: tuple[str, ...], p: dict[str, dict[str, float]]
    ) -> dict[str, dict[str, float]]:
        """The registry's effect mapping (what a scenario would say) for these parameter values."""
        eff: dict[str, dict[str, float]] = {}
        for lab, value in p.get("baseline", {}).items():
            effect, par = lab.split(".", 1)
            eff.setdefault(effect, {})[par] = value
        for effect in effects:
            given = p.get(effect, {})
            if effect == "periodic_error":
                periodic = {}
                for ax in ("x", "y"):
                    sin_deg = given.get(f"{ax}_sin_deg", 0.0)
                    cos_deg = given.get(f"{ax}_cos_deg", 0.0)
                    periodic[f"{ax}_amp_deg"] = float(np.hypot(sin_deg, cos_deg))
                    periodic[f"{ax}_phase_deg"] = float(np.degrees(np.arctan2(cos_deg, sin_deg)))
                eff[effect] = periodic
            else:
                eff[effect] = dict(given)
        return eff

    def predict_params(
        self, effects: tuple[str, ...], p: dict[str, dict[str, float]]
    ) -> NDArray[np.float64]:
        eff = self.effects_mapping(effects, p)
        model = StageEffectModel(self.bench, eff, [])
        fx = model.effect_set(())
        key = tuple(
            sorted(
                (geometry_effect, tuple(sorted(fx.values[geometry_effect].items())))
                for geometry_effect in _GEOMETRY_EFFECTS
                if geometry_effect in fx.on
            )
        )
        if self._geo_cache is None or self._geo_cache[0] != key:
            self._geo_cache = (key, StageGeometry.from_effects(self.bench, fx))
        pts = self.pts
        sim = simulate_stage(
            self.bench,
            fx,
            pts.stage_x_deg,
            pts.stage_y_deg,
            pts.dir_x,
            pts.dir_y,
            pts.temp_c,
            pts.t_s,
            rng=None,
            geometry=self._geo_cache[1],
        )
        return np.column_stack([sim[output] for output in self.outputs])

    def magnitude(self, fit: Fit, effect: str) -> Magnitude:
        return stage_magnitude(self, fit, effect)
