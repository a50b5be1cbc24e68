"""What a kinematic record knows of its reference sensor's own reading errors, and the reference
reading through it.

The reference is the lab's standard: its readings are taken as the table tilt. When a record models
the reference's own errors (a non-linearity, a zero and scale that change with temperature, a zero
that drifts with time; a diagnosis named them and the record adopted them), its readings are no
longer the table tilt: the table tilt is the reading with those errors taken out. Everything
reported from the reference (the levelling's read-back, the reference reading beside the corrected
tilt, validation, the reading stream) goes through this, with the raw reading kept beside it.

The reading model is the simulator's (docs/models.md §1):
reading = t·(1 + s_T·ΔT) + q·t² + z_T·ΔT + r·Δt, with ΔT the temperature above the record's
reference temperature and Δt the hours since the record's time origin; it is inverted exactly (a
quadratic in t).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.calibration.model import CalibrationModel, ReferenceErrorsState

STATE_KEY: Final = "reference_errors"


@dataclass(frozen=True)
class ReferenceErrors:
    """The reference sensor's reading errors a record models (zero where it does not)."""

    effects: tuple[str, ...]
    quad_per_deg: tuple[float, float]  # x, y
    zero_deg_per_k: tuple[float, float]
    scale_per_k: float
    drift_deg_per_h: tuple[float, float]
    temp_ref_c: float
    # POSIX seconds at which the drift is zero (the first point the record fitted)
    time_origin_s: float | None
    # the time the fitted points spanned (the drift is known over it)
    time_span_s: float | None = None

    @property
    def needs_temperature(self) -> bool:
        return "temperature_drift" in self.effects

    @property
    def needs_time(self) -> bool:
        return "time_drift" in self.effects

    def describe(self) -> str:
        """The model in the lab's words, for notes."""
        parts = []
        if "sensor_nonlinearity" in self.effects:
            parts.append(
                f"a quadratic term ({self.quad_per_deg[0]:.3g}, {self.quad_per_deg[1]:.3g} 1/deg)"
            )
        if self.needs_temperature:
            parts.append(
                f"a zero that changes by ({self.zero_deg_per_k[0]:.3g}, "
                f"{self.zero_deg_per_k[1]:.3g}) deg/K "
                f"and a scale by {self.scale_per_k:.3g} 1/K from {self.temp_ref_c:g} °C"
            )
        if self.needs_time:
            parts.append(
                f"a zero that drifts by ({self.drift_deg_per_h[0]:.3g}, "
                f"{self.drift_deg_per_h[1]:.3g}) deg/h from the time of the record's first point"
            )
        return "; ".join(parts)


def reference_errors(model: CalibrationModel) -> ReferenceErrors | None:
    """The record's model of its reference sensor's errors; None when it has none (its readings are
    the tilt)."""
    st = model.state.get(STATE_KEY)
    if not isinstance(st, dict) or not st.get("effects"):
        return None

    def v(name: str) -> float:
        param = model.parameters.get(name)
        return 0.0 if param is None else float(param.value)

    origin = st.get("time_origin_s")
    span = st.get("time_span_s")
    return ReferenceErrors(
        tuple(str(effect) for effect in st["effects"]),
        (v("sensor_nonlinearity.ref_x_per_deg"), v("sensor_nonlinearity.ref_y_per_deg")),
        (v("temperature_drift.ref_x_deg_per_k"), v("temperature_drift.ref_y_deg_per_k")),
        v("temperature_drift.ref_scale_per_k"),
        (v("time_drift.ref_x_deg_per_h"), v("time_drift.ref_y_deg_per_h")),
        float(st.get("temp_ref_c", 20.0)),
        None if origin is None else float(origin),
        None if span is None else float(span),
    )


def state_of(
    effects: tuple[str, ...],
    temp_ref_c: float,
    time_origin_s: float | None,
    time_span_s: float | None = None,
) -> ReferenceErrorsState:
    """What a model's state keeps of its reference model (its parameters are the model's own)."""
    return {
        "effects": list(effects),
        "temp_ref_c": temp_ref_c,
        "time_origin_s": time_origin_s,
        "time_span_s": time_span_s,
    }


def extrapolation_note(errors: ReferenceErrors, t_s: float) -> str | None:
    """What to say of a reading read through a drift far beyond the time the record fitted it over
    (more than the span again after its last point): the drift is then extrapolated."""
    if not errors.needs_time or errors.time_origin_s is None or errors.time_span_s is None:
        return None
    after = t_s - errors.time_origin_s
    if after <= 2.0 * max(errors.time_span_s, 1.0):
        return None
    return (
        "the reference's drift is extrapolated: the record fitted it over "
        f"{errors.time_span_s:.0f} s, this reading is {after:.0f} s after its first point"
    )


def _invert(
    raw: NDArray[np.float64], gain: NDArray[np.float64], quad: float, offset: NDArray[np.float64]
) -> NDArray[np.float64]:
    """t with gain·t + quad·t² + offset = raw: the root near raw (stable form of the quadratic
    formula)."""
    const = offset - raw
    disc = np.sqrt(np.clip(gain * gain - 4.0 * quad * const, 0.0, None))
    t: NDArray[np.float64] = -2.0 * const / (gain + disc)
    return t


def true_reading(
    errors: ReferenceErrors,
    raw_x_deg: ArrayLike,
    raw_y_deg: ArrayLike,
    temp_c: ArrayLike | None = None,
    t_s: ArrayLike | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The table tilt a reference reading stands for: the reading with the modelled errors taken
    out.

    `temp_c` is needed when the record models a temperature effect and `t_s` (POSIX seconds) when it
    models a drift; without them the result is NaN (the caller says why)."""
    rx = np.asarray(raw_x_deg, dtype=float)
    ry = np.asarray(raw_y_deg, dtype=float)
    shape = np.broadcast_shapes(rx.shape, ry.shape)
    nan = np.full(shape, np.nan)
    dT: NDArray[np.float64] = np.zeros(shape)
    if errors.needs_temperature:
        dT = (
            nan
            if temp_c is None
            else np.broadcast_to(np.asarray(temp_c, dtype=float) - errors.temp_ref_c, shape)
        )
    dt_h: NDArray[np.float64] = np.zeros(shape)
    if errors.needs_time:
        dt_h = (
            nan
            if t_s is None or errors.time_origin_s is None
            else np.broadcast_to(
                (np.asarray(t_s, dtype=float) - errors.time_origin_s) / 3600.0, shape
            )
        )
    gain = 1.0 + errors.scale_per_k * dT
    out = []
    for raw, axis in ((rx, 0), (ry, 1)):
        offset = errors.zero_deg_per_k[axis] * dT + errors.drift_deg_per_h[axis] * dt_h
        out.append(_invert(np.broadcast_to(raw, shape), gain, errors.quad_per_deg[axis], offset))
    return out[0], out[1]


def needs_note(errors: ReferenceErrors, have_temp: bool, have_time: bool) -> str | None:
    """Why a reference reading cannot go through the record's model (None when it can)."""
    if errors.needs_temperature and not have_temp:
        return (
            "the record models the reference sensor's temperature effect, and no temperature "
            "came with the reading"
        )
    if errors.needs_time and not have_time:
        return "the record models the reference sensor's drift, and the reading has no time"
    return None
