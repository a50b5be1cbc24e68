"""What `GET /tilt` and the live reading stream serve of a bench's latest readings: the corrected
table tilt through the active calibration record, when a reading is stale, and the temperature.

One place for each, used by both, so they serve the same numbers by the same rules.
"""

from __future__ import annotations

import weakref
from typing import TYPE_CHECKING, Any

import numpy as np

from service.calibration.budget import combine, reading_components
from service.calibration.uncertainty import COVERAGE, dof_of_coverage_factor
from service.instruments.base import Reading
from service.io.columns import K_OUTPUTS

if TYPE_CHECKING:
    from service.bench.runtime import BenchRuntime

STALE_INTERVALS = 3  # a reading older than this many output intervals (plus STALE_SLACK_S) is stale
STALE_SLACK_S = 0.25  # real seconds: a loaded machine's delay in handing a reading on
# Real seconds: a bench sped up past one reading per this interval has at most one reading corrected per
# interval for `GET /tilt` and the stream (the stream's producer thins its messages the same way).
MIN_CORRECTION_GAP_S = 0.004


def stale_after_s(bench: BenchRuntime, role: str) -> float:
    """Real seconds after which the role's latest reading is stale (the sensor counts as silent)."""
    return STALE_INTERVALS * bench.clock.real_seconds(bench.output_interval_s(role)) + STALE_SLACK_S


def sensor_temp_c(meas: Reading | None, ref: Reading | None) -> float | None:
    """The measurement sensor's temperature, else the reference sensor's, else none."""
    if meas is not None and meas.temp_c is not None:
        return meas.temp_c
    return ref.temp_c if ref is not None else None


def corrected_tilt(active: Any, meas: Reading) -> dict[str, Any]:
    """Table tilt in the reference sensor's frame with its expanded uncertainty (GUM, 95 % coverage) from
    the record's covariance: {"x_deg", "y_deg", "u_x_deg", "u_y_deg", "k", "k_y", "coverage_probability"};
    `k` is the coverage factor of u_x_deg and `k_y` that of u_y_deg, Student's t at the effective
    degrees of freedom (Welch-Satterthwaite), near 2 for a well-determined record; an uncertainty the
    method cannot give is None, and so is its factor. `active` is the job manager's ActiveModel of the bench.

    The fit's part (covariance and reading noise, from the method) combines with the rest of the record's
    uncertainty budget: the reference standards' u = U/k, the sensors' resolution, the temperature's influence."""
    out = active.method.correct(active.model, {"meas_x_deg": np.array([meas.x_deg], dtype=float),
                                               "meas_y_deg": np.array([meas.y_deg], dtype=float)})

    def u(k: str) -> float | None:
        return None if k not in out or not np.isfinite(out[k][0]) else float(out[k][0])

    others = reading_components(getattr(active, "budget", None))
    expanded: dict[str, float | None] = {}
    factors: dict[str, float | None] = {}
    for axis, key in (("x", K_OUTPUTS[0]), ("y", K_OUTPUTS[1])):
        U_fit, k_fit = u(f"u_tilt_{axis}_deg"), u(key)
        if U_fit is None or k_fit is None:
            expanded[axis], factors[axis] = U_fit, None if U_fit is None else k_fit
            continue
        c = combine(np.array([U_fit / k_fit]), dof_of_coverage_factor(np.array([k_fit]), COVERAGE), others, COVERAGE)
        expanded[axis], factors[axis] = float(c.U[0]), float(c.k[0])
    return {"x_deg": float(out["tilt_x_deg"][0]), "y_deg": float(out["tilt_y_deg"][0]),
            "u_x_deg": expanded["x"], "u_y_deg": expanded["y"], "k": factors["x"], "k_y": factors["y"],
            "coverage_probability": COVERAGE}


# Per bench: the last reading corrected, the record it went through and the result.
_LAST_CORRECTED: weakref.WeakKeyDictionary[BenchRuntime, tuple[Reading, Any, dict[str, Any]]] = weakref.WeakKeyDictionary()


def corrected_once(bench: BenchRuntime, active: Any, meas: Reading) -> dict[str, Any]:
    """`corrected_tilt` of the bench's reading, computed once per new reading (or newly active record):
    the sensor sends tens of readings a second, `GET /tilt` and the stream may ask thousands of times.
    The answer is shared between callers; nobody changes it."""
    last = _LAST_CORRECTED.get(bench)
    if last is not None and last[0] is meas and last[1] is active:
        return last[2]
    table = corrected_tilt(active, meas)
    _LAST_CORRECTED[bench] = (meas, active, table)
    return table


def corrected_reading(bench: BenchRuntime, active: Any, meas: Reading) -> tuple[Reading, dict[str, Any]]:
    """The reading `GET /tilt` serves and its corrected tilt: `meas`, the bench's latest, through
    `corrected_once`; on a bench sped up past one reading per MIN_CORRECTION_GAP_S of real time, the
    last reading corrected while `meas` came less than that after it (a simulation at 20 times real
    time sends a reading a millisecond, and each would cost a correction). A bench at its own pace
    always gets its latest reading corrected."""
    last = _LAST_CORRECTED.get(bench)
    if (last is not None and last[1] is active and last[0].role == meas.role
            and bench.clock.real_seconds(bench.output_interval_s(meas.role)) < MIN_CORRECTION_GAP_S
            and 0.0 <= bench.clock.real_seconds(meas.bench_s - last[0].bench_s) < MIN_CORRECTION_GAP_S * 0.999):
        return last[0], last[2]
    return meas, corrected_once(bench, active, meas)


def in_calibrated_range(active: Any, table: dict[str, Any] | None) -> bool | None:
    """Whether a corrected table tilt lies within the table tilts the active record was fitted on (per axis,
    the reference sensor's frame); None when there is no corrected tilt or the record states no range."""
    seen = getattr(active, "table_tilt_range_deg", None) if active is not None else None
    if table is None or seen is None:
        return None
    return bool(seen["x"][0] <= table["x_deg"] <= seen["x"][1] and seen["y"][0] <= table["y_deg"] <= seen["y"][1])


def calibrated_range_note(active: Any, table: dict[str, Any]) -> str:
    """What `note` says of a corrected tilt outside the calibrated range: served, but extrapolated."""
    seen = active.table_tilt_range_deg
    return (f"outside the calibrated range of record {active.record_id} (x {seen['x'][0]:.4g} to {seen['x'][1]:.4g}°,"
            f" y {seen['y'][0]:.4g} to {seen['y'][1]:.4g}°): the corrected tilt is extrapolated")


def calibration_json(active: Any) -> dict[str, Any] | None:
    """The `calibration` object of /tilt and the stream's snapshot: which record corrects, and its status."""
    if active is None:
        return None
    return {"record_id": active.record_id, "version": active.version, "method": active.method_name,
            "status": active.status}
