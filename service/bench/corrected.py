"""What `GET /tilt` and the live reading stream serve of a bench's latest readings: the corrected
table tilt through the active calibration record, when a reading is stale, and the temperature.

One place for each, used by both, so they serve the same numbers by the same rules.
"""

from __future__ import annotations

import weakref
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, NotRequired, TypedDict

import numpy as np

from service.bench.settled import SETTLING_RULE
from service.calibration.budget import Component, combine, reading_components
from service.calibration.methods.stage.reference import extrapolation_note, needs_note, true_reading
from service.calibration.registry import Columns
from service.calibration.uncertainty import COVERAGE, dof_of_coverage_factor, mean_type_a
from service.instruments.base import Reading
from service.io.columns import K_OUTPUTS

if TYPE_CHECKING:
    from service.bench.runtime import BenchRuntime

STALE_INTERVALS = 3  # a reading older than this many output intervals (plus STALE_SLACK_S) is stale
STALE_SLACK_S = 0.25  # real seconds: a loaded machine's delay in handing a reading on
# Real seconds: a bench sped up past one reading per this interval has at most one reading corrected
# per interval for `GET /tilt` and the stream (the stream's producer thins its messages the same
# way).
MIN_CORRECTION_GAP_S = 0.004


class TableTilt(TypedDict):
    """A table tilt (degrees, the reference sensor's frame); None where it is not known."""

    x_deg: float | None
    y_deg: float | None


class CorrectedTilt(TypedDict):
    """The corrected table tilt `GET /tilt` and the stream serve (degrees), with per axis its
    standard and expanded uncertainty, coverage factor and degrees of freedom (None: unknown, or
    infinite degrees of freedom); `u_x_deg`, `u_y_deg`, `k`, `k_y` are the expanded uncertainties
    and their factors under their former names. An averaged tilt adds `n_readings`, `window_s`."""

    x_deg: float | None
    y_deg: float | None
    standard_uncertainty_x_deg: float | None
    expanded_uncertainty_x_deg: float | None
    coverage_factor_x: float | None
    degrees_of_freedom_x: float | None
    standard_uncertainty_y_deg: float | None
    expanded_uncertainty_y_deg: float | None
    coverage_factor_y: float | None
    degrees_of_freedom_y: float | None
    coverage_probability: float | None
    u_x_deg: float | None
    u_y_deg: float | None
    k: float | None
    k_y: float | None
    n_readings: NotRequired[int]
    window_s: NotRequired[float]


class ReferenceTableTilt(TypedDict):
    """The table tilt the reference sensor's reading stands for through the active record's model
    of its errors (degrees; None, and `note` says why, without what the model needs)."""

    x_deg: float | None
    y_deg: float | None
    record_id: int
    note: NotRequired[str]


class CalibrationInUse(TypedDict):
    """The `calibration` object of /tilt and the stream's snapshot: the record that corrects."""

    record_id: int
    version: int
    method: str
    status: str
    reading_noise: str | None


# the standard uncertainty, expanded uncertainty, coverage factor and degrees of freedom of an axis
_AxisUncertainty = tuple[float | None, float | None, float | None, float | None]


def stale_after_s(bench: BenchRuntime, role: str) -> float:
    """Real seconds after which the role's latest reading is stale (the sensor counts as silent)."""
    return STALE_INTERVALS * bench.clock.real_seconds(bench.output_interval_s(role)) + STALE_SLACK_S


def sensor_temp_c(meas: Reading | None, ref: Reading | None) -> float | None:
    """The measurement sensor's temperature, else the reference sensor's, else none."""
    if meas is not None and meas.temp_c is not None:
        return meas.temp_c
    return ref.temp_c if ref is not None else None


def corrected_tilt(active: Any, meas: Reading) -> CorrectedTilt:
    """Table tilt in the reference sensor's frame with its uncertainties (GUM, 95 % coverage), per
    axis: the standard uncertainty u, the expanded U = k·u, the coverage factor k (Student's t at
    the Welch-Satterthwaite effective degrees of freedom) and those degrees of freedom (None:
    infinite); `u_x_deg`, `u_y_deg`, `k`, `k_y` repeat the expanded uncertainties and their factors
    under their former names. An uncertainty the method cannot give is None, and so are its factor
    and degrees of freedom. `active` is the job manager's ActiveModel of the bench.

    The fit's part is the record's parameter covariance with the noise of ONE reading of the
    measurement sensor (`ActiveModel.live_model`: pooled from the readings the record's job stored
    at its points); the reference sensor's noise is already in the parameters. It combines with the
    rest of the record's uncertainty budget: the reference standards' u = U/k, the sensors'
    resolution, the temperature's influence."""
    model = getattr(active, "live_model", active.model)
    out = active.method.correct(
        model,
        {
            "meas_x_deg": np.array([meas.x_deg], dtype=float),
            "meas_y_deg": np.array([meas.y_deg], dtype=float),
        },
    )
    table: TableTilt = {
        "x_deg": float(out["tilt_x_deg"][0]),
        "y_deg": float(out["tilt_y_deg"][0]),
    }
    parts = {
        axis: _fit_part(out, axis, key) for axis, key in (("x", K_OUTPUTS[0]), ("y", K_OUTPUTS[1]))
    }
    return with_uncertainties(table, parts, reading_components(getattr(active, "budget", None)))


def averaged_tilt(active: Any, readings: list[Reading], window_s: float) -> CorrectedTilt:
    """The mean of `readings` (the measurement sensor's, at one stand of the stage) corrected
    through the active record, with the uncertainty of that mean: per axis, the Type A uncertainty
    of the mean of the corrected readings (`mean_type_a`: their own scatter, their correlation
    allowed for) combined with the parameters' part at the mean (which does not average down) and
    the rest of the record's budget (the standards, resolutions, temperature: none of them averages
    down either). Adds `n_readings` and `window_s`."""
    mx = np.array([reading.x_deg for reading in readings], dtype=float)
    my = np.array([reading.y_deg for reading in readings], dtype=float)
    each = active.method.correct(
        getattr(active, "live_model", active.model), {"meas_x_deg": mx, "meas_y_deg": my}
    )
    at_mean = active.method.correct(
        getattr(active, "parameter_model", active.model),
        {"meas_x_deg": np.array([mx.mean()]), "meas_y_deg": np.array([my.mean()])},
    )
    means: dict[str, float] = {}
    parts: dict[str, tuple[float, float] | None] = {}
    others = reading_components(getattr(active, "budget", None))
    scatter: dict[str, list[Component]] = {}
    for axis, k_key in (("x", K_OUTPUTS[0]), ("y", K_OUTPUTS[1])):
        mean = mean_type_a(each[f"tilt_{axis}_deg"])
        means[axis] = mean.mean
        parts[axis] = _fit_part(at_mean, axis, k_key)
        # the mean's Type A, with its own degrees of freedom, beside the record's components
        scatter[axis] = [
            Component(
                "readings",
                f"mean of {len(readings)} readings, {axis}",
                mean.u,
                mean.dof,
                "student-t",
                "A",
            )
        ]
    table: TableTilt = {"x_deg": means["x"], "y_deg": means["y"]}
    out = with_uncertainties(table, parts, others, scatter)
    out.update({"n_readings": len(readings), "window_s": window_s})
    return out


def _fit_part(out: Columns, axis: str, k_key: str) -> tuple[float, float] | None:
    """(u, degrees of freedom) of the method's part of one axis, from its expanded uncertainty and
    factor."""

    def value(key: str) -> float | None:
        return None if key not in out or not np.isfinite(out[key][0]) else float(out[key][0])

    expanded, factor = value(f"u_tilt_{axis}_deg"), value(k_key)
    if expanded is None or factor is None:
        return None
    return _standard_and_dof(expanded, factor)


def _standard_and_dof(expanded: float, factor: float) -> tuple[float, float]:
    """(u = U/k, the degrees of freedom the 95 % coverage factor k is Student's t at)."""
    return expanded / factor, float(dof_of_coverage_factor(np.array([factor]), COVERAGE)[0])


def with_uncertainties(
    table: TableTilt,
    parts: Mapping[str, tuple[float, float] | None],
    others: list[Component],
    per_axis: Mapping[str, list[Component]] | None = None,
) -> CorrectedTilt:
    """`table` with each axis's standard and expanded uncertainty, coverage factor and degrees of
    freedom: the fit's part (u, ν) of each axis (x and y) combined with the budget's other
    components and the axis's own (`per_axis`) by the GUM's law and Welch-Satterthwaite."""
    u_x, expanded_x, k_x, dof_x = _axis_uncertainty(parts["x"], others, per_axis, "x")
    u_y, expanded_y, k_y, dof_y = _axis_uncertainty(parts["y"], others, per_axis, "y")
    return {
        "x_deg": table["x_deg"],
        "y_deg": table["y_deg"],
        "standard_uncertainty_x_deg": u_x,
        "expanded_uncertainty_x_deg": expanded_x,
        "coverage_factor_x": k_x,
        "degrees_of_freedom_x": dof_x,
        "standard_uncertainty_y_deg": u_y,
        "expanded_uncertainty_y_deg": expanded_y,
        "coverage_factor_y": k_y,
        "degrees_of_freedom_y": dof_y,
        "coverage_probability": COVERAGE,
        # the former names, kept for one release: the expanded uncertainties and their factors
        "u_x_deg": expanded_x,
        "u_y_deg": expanded_y,
        "k": k_x,
        "k_y": k_y,
    }


def _axis_uncertainty(
    part: tuple[float, float] | None,
    others: list[Component],
    per_axis: Mapping[str, list[Component]] | None,
    axis: str,
) -> _AxisUncertainty:
    """One axis's (u, U, k, degrees of freedom): all None without the fit's part; the degrees of
    freedom None where infinite."""
    if part is None:
        return None, None, None, None
    own = (per_axis or {}).get(axis, [])
    combined = combine(np.array([part[0]]), part[1], [*others, *own], COVERAGE)
    dof = float(combined.dof_eff[0]) if np.isfinite(combined.dof_eff[0]) else None
    return float(combined.u[0]), float(combined.U[0]), float(combined.k[0]), dof


def from_expanded(
    table: TableTilt,
    expanded: Mapping[str, float | None],
    factors: Mapping[str, float | None],
    coverage: float | None,
) -> CorrectedTilt:
    """`table` with the uncertainties of every name, from the expanded uncertainties and coverage
    factors alone (what the stream's history keeps): u = U/k, and the degrees of freedom k is
    Student's t at."""
    parts: dict[str, tuple[float, float] | None] = {}
    for axis in ("x", "y"):
        expanded_u, k = expanded[axis], factors[axis]
        parts[axis] = (
            None if expanded_u is None or k is None or k <= 0 else _standard_and_dof(expanded_u, k)
        )
    out = with_uncertainties(table, parts, [])
    out["coverage_probability"] = coverage
    return out


# Per bench: the last reading corrected, the record it went through and the result.
_LAST_CORRECTED: weakref.WeakKeyDictionary[BenchRuntime, tuple[Reading, Any, CorrectedTilt]] = (
    weakref.WeakKeyDictionary()
)


def corrected_once(bench: BenchRuntime, active: Any, meas: Reading) -> CorrectedTilt:
    """`corrected_tilt` of the bench's reading, computed once per new reading (or newly active
    record): the sensor sends tens of readings a second, `GET /tilt` and the stream may ask
    thousands of times. The answer is shared between callers; nobody changes it."""
    last = _LAST_CORRECTED.get(bench)
    if last is not None and last[0] is meas and last[1] is active:
        return last[2]
    table = corrected_tilt(active, meas)
    _LAST_CORRECTED[bench] = (meas, active, table)
    return table


def corrected_reading(
    bench: BenchRuntime, active: Any, meas: Reading
) -> tuple[Reading, CorrectedTilt]:
    """The reading `GET /tilt` serves and its corrected tilt: `meas`, the bench's latest, through
    `corrected_once`; on a bench sped up past one reading per MIN_CORRECTION_GAP_S of real time, the
    last reading corrected while `meas` came less than that after it (a simulation at 20 times real
    time sends a reading a millisecond, and each would cost a correction). A bench at its own pace
    always gets its latest reading corrected."""
    last = _LAST_CORRECTED.get(bench)
    if (
        last is not None
        and last[1] is active
        and last[0].role == meas.role
        and bench.clock.real_seconds(bench.output_interval_s(meas.role)) < MIN_CORRECTION_GAP_S
        and 0.0
        <= bench.clock.real_seconds(meas.bench_s - last[0].bench_s)
        < MIN_CORRECTION_GAP_S * 0.999
    ):
        return last[0], last[2]
    return meas, corrected_once(bench, active, meas)


def reference_tilt(
    active: Any, ref: Reading | None, temp_c: float | None
) -> ReferenceTableTilt | None:
    """The reference sensor's reading through the active record's model of its own errors (a
    non-linearity, a temperature effect, a drift): the table tilt it stands for, {"x_deg", "y_deg",
    "record_id"}; None when there is no reading or the record models none of them (its readings are
    then the table tilt). Without the temperature or time the model needs, the angles are None and
    `note` says why."""
    errors = getattr(active, "reference", None) if active is not None else None
    if errors is None or ref is None or ref.x_deg is None or ref.y_deg is None:
        return None
    temp = ref.temp_c if ref.temp_c is not None else temp_c
    why = needs_note(errors, temp is not None, True)
    if why is not None:
        return {"x_deg": None, "y_deg": None, "record_id": active.record_id, "note": why}
    t_s = ref.time_utc.timestamp()
    x, y = true_reading(errors, ref.x_deg, ref.y_deg, temp, t_s)
    out: ReferenceTableTilt = {"x_deg": float(x), "y_deg": float(y), "record_id": active.record_id}
    if (far := extrapolation_note(errors, t_s)) is not None:
        out["note"] = far
    return out


def in_calibrated_range(active: Any, table: CorrectedTilt | None) -> bool | None:
    """Whether a corrected table tilt lies within the table tilts the active record was fitted on
    (per axis, the reference sensor's frame); None when there is no corrected tilt or the record
    states no range."""
    seen = getattr(active, "table_tilt_range_deg", None) if active is not None else None
    if table is None or seen is None:
        return None
    return bool(
        seen["x"][0] <= table["x_deg"] <= seen["x"][1]
        and seen["y"][0] <= table["y_deg"] <= seen["y"][1]
    )


def calibrated_range_note(active: Any, table: CorrectedTilt) -> str:
    """What `note` says of a corrected tilt outside the calibrated range: served, but
    extrapolated."""
    seen = active.table_tilt_range_deg
    return (
        f"outside the calibrated range of record {active.record_id} (x {seen['x'][0]:.4g} to "
        f"{seen['x'][1]:.4g}°,"
        f" y {seen['y'][0]:.4g} to {seen['y'][1]:.4g}°): the corrected tilt is extrapolated"
    )


def calibration_json(active: Any) -> CalibrationInUse | None:
    """The `calibration` object of /tilt and the stream's snapshot: which record corrects, and its
    status."""
    if active is None:
        return None
    return {
        "record_id": active.record_id,
        "version": active.version,
        "method": active.method_name,
        "status": active.status,
        "reading_noise": getattr(active, "reading_noise_source", None),
    }


def _at_stand(kept: list[Reading], still: float, meas: Reading) -> list[Reading]:
    """The kept readings of both axes made while the stage stood where it stands, up to `meas`."""
    return [
        reading
        for reading in kept
        if still < reading.bench_s <= meas.bench_s
        and reading.x_deg is not None
        and reading.y_deg is not None
    ]


def _window_begins(
    bench: BenchRuntime, active: Any, still: float, stand: list[Reading], meas: Reading
) -> tuple[float | None, str]:
    """Where the averaging window may begin, and how the note names that moment: the end of the
    stage's last move or, with a known reading noise, when the readings settled after it (None,
    and why, while they have not)."""
    noise = getattr(active, "reading_noise", None)
    if not (noise is not None and noise.sigma_deg > 0):
        return still, "the end of the stage's last move"
    # the table rings and the sensor lags after a move: the window starts once the readings have
    # settled
    settled = bench.stand_settling.settled_since(
        still,
        np.array([[reading.x_deg, reading.y_deg] for reading in stand], dtype=float),
        [reading.bench_s for reading in stand],
        noise.sigma_deg,
    )
    if settled is None:
        return None, (
            "the readings since the end of the stage's last move "
            f"({meas.bench_s - still:.3g} s ago) have not yet settled within one reading's "
            f"noise ({noise.sigma_deg:.2g} deg, {SETTLING_RULE}): no average of a transient"
        )
    return settled, "when the readings settled after the stage's last move"


def averaged_at_stand(
    bench: BenchRuntime, active: Any, meas: Reading, average_s: float
) -> tuple[CorrectedTilt | None, str]:
    """`GET /tilt?average_s`: the averaged table tilt over the readings up to `meas` (the latest)
    since the readings settled at the stage's present stand, and what `note` says of its window."""
    still = bench.pose.still_since_bench_s
    if bench.pose.moving or still is None:
        return (
            None,
            "the stage is moving: no average (average_s takes readings while the stage stands)",
        )
    # the driver keeps the latest few thousand
    kept = bench.readings_after("measurement_sensor", float("-inf"))
    stand = _at_stand(kept, still, meas)
    began, since = _window_begins(bench, active, still, stand, meas)
    if began is None:
        return None, since
    start = max(meas.bench_s - average_s, began)
    readings = [reading for reading in stand if reading.bench_s > start]
    window_s = meas.bench_s - start
    if len(readings) < 2:
        return None, (
            f"{len(readings)} reading(s) since {since} ({window_s:.3g} s ago): an average needs "
            "two or more"
        )
    reach = (
        ""
        if start > began or window_s >= average_s
        else f"; the window starts {since}, {window_s:.3g} s before the latest reading"
    )
    if kept[0].bench_s > start:  # the oldest reading kept is younger than the window
        window_s = meas.bench_s - kept[0].bench_s
        reach += f"; only the last {window_s:.3g} s of readings are kept"
    table = averaged_tilt(active, readings, window_s)
    return table, f"mean of {len(readings)} readings over {window_s:.3g} s{reach}"
