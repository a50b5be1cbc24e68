"""The fitted calibration model: one record layout for every kind and method (MODEL.json).

A model carries what a metrologist needs to trust and reuse it: named parameters with
units, their covariance (with the order of the names), the columns it was fitted on, the
fit residuals and statistics, and notes on what was fixed or merged and why. The JSON
layout is documented by docs/model.schema.json.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NotRequired, TypedDict

import numpy as np
from numpy.typing import NDArray

from service.errors import InputError

FORMAT_VERSION = 1


class ParameterJSON(TypedDict):
    """A parameter as MODEL.json keeps it: its value (null where not finite) and unit; `fixed` and
    `note` only when it was held."""

    value: float | None
    unit: str
    fixed: NotRequired[bool]
    note: NotRequired[str]


class ResidualColumn(TypedDict):
    """One residual column's RMS and max |r| (the model's residual unit), and its values where
    kept."""

    rms: float
    max_abs: float
    values: NotRequired[list[float]]


class ResidualSummary(TypedDict, total=False):
    """MODEL.json `residuals`: their unit and each column's summary (empty in a model without
    them)."""

    unit: str
    columns: dict[str, ResidualColumn]


class StageBenchJSON(TypedDict, total=False):
    """The stage hardware as a stage model's state keeps it (service.physics.stage.StageBench's
    fields)."""

    upper_gear_ratio: float
    lower_gear_ratio: float
    step_angle_deg: float
    microsteps: int
    travel_deg: float
    meas_flip: str
    temp_ref_c: float


class ReferenceErrorsState(TypedDict):
    """What a stage model's state keeps of its model of the reference sensor's errors (their
    parameters are the model's own)."""

    effects: list[str]
    temp_ref_c: float
    time_origin_s: float | None
    time_span_s: float | None


class ConstantErrorArc(TypedDict):
    """Rotation: one branch's θ bias from the outputs' constant errors, a line in θ about the
    arc's centre (degrees) with its covariance."""

    branch: str
    centre_deg: float
    half_width_deg: float
    coefficients_deg: list[float]
    coefficient_covariance_deg2: list[list[float]]


class TurntableState(TypedDict, total=False):
    """Turntable models' state: one reading's noise (arcsec) and its degrees of freedom, the fit's
    degrees of freedom."""

    reading_sigma: float | None
    reading_sigma_dof: float
    dof: float


class ScaleState(TypedDict, total=False):
    """Scale models' state: the polynomial's degree, one reading's noise (counts; None without
    degrees of freedom), the fit's degrees of freedom."""

    degree: int
    reading_sigma_counts: float | None
    dof: float


class RotationState(TypedDict, total=False):
    """Rotation models' state: the outputs' noise (`sigma_s`) and, where seen, the θ bias of
    their constant errors per branch."""

    sigma_s: float | None
    theta_constant_output_errors: list[ConstantErrorArc]


class ReadingNoiseState(TypedDict, total=False):
    """Stage models: one measurement reading's noise (degrees) and where it comes from; the
    reference's where the two sensors' noise was separated."""

    meas_reading_standard_uncertainty_deg: float
    meas_reading_dof: float
    meas_reading_noise_source: str
    ref_reading_standard_uncertainty_deg: float


class StageState(ReadingNoiseState, total=False):
    """What every stage model's state keeps: its bench and, with a measurement sensor fitted, the
    sensor's sign, the fit's residual sigma (degrees) and degrees of freedom."""

    has_meas: bool
    bench: StageBenchJSON
    bench_source: str
    meas_sign: list[float]
    meas_sigma_deg: float | None
    meas_dof: float


class KinematicState(StageState, total=False):
    """The kinematic chain's state: whether it corrects, the chain's parameters, the approach
    direction, and its model of the reference sensor's errors."""

    chain_parameters: list[str]
    approach: list[float]
    reference_errors: ReferenceErrorsState


class HomographyState(StageState, total=False):
    """The homography's state: how the off-axis term is taken (exact or paper)."""

    offaxis: str


class CouplingState(StageState, total=False):
    """The coupling method's state: the measurement sensor's misfit RMS and its envelope over the
    pose, per axis (degrees), with the bound on its size relative to that envelope; models made
    before kept one bound per axis, how fast it grows with the tilt and the range it holds over."""

    meas_misfit_rms_deg: list[float]
    meas_misfit_p95_deg: list[float]
    meas_misfit_slope: list[list[float]]
    meas_misfit_range_deg: dict[str, list[float]]
    # the misfit's envelope over the pose (per axis: the plane [a, b, c] of a + b·X + c·Y, the
    # scatter about it) and the 95 % bound and RMS of |misfit| / envelope over the points
    meas_misfit_plane_deg: list[list[float]]
    meas_misfit_scatter_deg: list[float]
    meas_misfit_score_p95: list[float]
    meas_misfit_score_rms: list[float]


class AxisTransformState(StageState, total=False):
    """The axis-transform method's state: the corrected tilt's bias its model cannot absorb (no
    zero offsets) and the random part of one reading about it, per axis (degrees)."""

    meas_uncorrected_bias_deg: list[float]
    meas_axis_reading_standard_uncertainty_deg: list[float]


class AdoptedEffectsState(TypedDict, total=False):
    """A model a diagnosis's effects were adopted into: the effects and the diagnosis they came
    from (service.discrepancy.adopt)."""

    added_effects: list[str]
    diagnosis: dict[str, object]


class ModelState(
    TurntableState,
    ScaleState,
    RotationState,
    KinematicState,
    HomographyState,
    CouplingState,
    AxisTransformState,
    AdoptedEffectsState,
    total=False,
):
    """MODEL.json `state`: what a method keeps to apply its model beyond the parameters, each
    method's keys as its part above states them (JSON-serialisable)."""


class ModelOptions(TypedDict, total=False):
    """MODEL.json `options`: the fit options a method was given (turntable: the rotation between
    a pair's positions; homography: the points and off-axis term; kinematic: the loss and the
    effects added)."""

    rotation_deg: float
    points: str
    offaxis: str
    loss: str
    effects: list[str]


class FitStats(TypedDict):
    """A fit's degrees of freedom and residual sigma (degrees; None without degrees of freedom)."""

    dof: int
    sigma_deg: float | None


class FTestResult(TypedDict):
    """An F-test of one added polynomial term: F(1, dof) (None where the larger fit leaves no
    residual), its degrees of freedom [1, dof], the upper-tail p and whether p < 0.05."""

    F: float | None
    dof: list[int]
    p_value: float
    significant_at_5pct: bool


class DegreeFTest(TypedDict, total=False):
    """Scale: an F-test of a degree against the one below (`against_degree`) or of the next degree
    (`degree`); the test's own keys only where the larger fit had degrees of freedom."""

    against_degree: int
    degree: int
    F: float | None
    dof: list[int]
    p_value: float
    significant_at_5pct: bool


class ReadingOnAngle(TypedDict):
    """Scale: the paper's direction, reading = Σ a_j angle^j (counts, arcsec), beside the model;
    `arcsec_per_count` for degree 1 only."""

    coefficients: list[float]
    units: list[str]
    standard_errors: list[float] | None
    residual_norm_counts: float
    residual_sigma_counts: float | None
    arcsec_per_count: NotRequired[float]


class ChainFitStats(TypedDict):
    """Kinematic: the chain fit's degrees of freedom, residual sigma (degrees), convergence,
    function evaluations, loss and the scaled Jacobian's singular values."""

    dof: int
    sigma_deg: float
    converged: bool
    nfev: int
    loss: str
    scaled_jacobian_singular_values: list[float]


class MeasFitStats(TypedDict):
    """Kinematic: the measurement sensor's fit, its degrees of freedom (of the residuals and of the
    covariance), residual sigma (degrees) and function evaluations."""

    dof: int
    covariance_dof: float
    sigma_deg: float
    nfev: int


class CommonFit(TypedDict, total=False):
    """What several methods' `fit` state: the points, degrees of freedom, convergence and residual
    sigma (arcsec)."""

    n_points: int
    dof: int
    converged: bool
    residual_sigma_arcsec: float | None


class TurntableFit(CommonFit, total=False):
    """Turntable: the pairs, iterations and start values, the azimuths and reference tilts seen, the
    pair rotation held, the reading noise (and where from) and the reference's sigma (arcsec)."""

    n_pairs: int
    iterations: int
    initial: dict[str, float]
    initial_from: str
    n_azimuths: int
    n_reference_tilts: int
    rotation_deg: float
    reading_sigma: float
    reading_sigma_from: str
    reference_sigma_arcsec: float


class ScaleFit(CommonFit, total=False):
    """Scale: the reference column and direction, the residual norm, standard errors, measuring
    unit, reading range, the F-tests, the paper's direction and monotonicity."""

    reference_column: str
    direction: str
    residual_norm_arcsec: float
    standard_errors: dict[str, float] | None
    measuring_unit_arcsec_per_count: float
    reading_range: list[float]
    measuring_unit_note: str
    f_test_highest_term: DegreeFTest
    f_test_next_degree: DegreeFTest
    reading_on_angle: ReadingOnAngle
    monotonic_over_range: bool


class RotationFit(CommonFit, total=False):
    """Rotation: the outputs' noise, the plane residual, the estimator, where Sz came from and how
    many points took eq. (6)."""

    sigma_s: float | None
    plane_residual: ResidualColumn
    estimator: str
    sz_source: str
    n_replaced_by_eq6: int


class StageFit(CommonFit, total=False):
    """Every stage method: the residual sigma (degrees; coupling) and the table tilts fitted on per
    axis [min, max] (added by the job or command that fitted it)."""

    sigma_deg: float | None
    table_tilt_range_deg: dict[str, list[float]] | None


class HomographyFit(StageFit, total=False):
    """Homography: H1's points and statistics, the off-axis term, levelling's residual on every
    point, eq. (10) forwards against the exact inverse, and H2's statistics."""

    n_points_h1: int
    points: str
    offaxis: str
    h1: FitStats
    h2: FitStats
    levelling_residual_all_points: ResidualSummary
    offaxis_forward_vs_exact: dict[str, float]


class AxisTransformFit(StageFit, total=False):
    """Axis transform: the statistics of the stage -> reference and measurement -> reference
    fits."""

    stage_to_ref: FitStats
    meas_to_ref: FitStats


class KinematicFit(StageFit, total=False):
    """Kinematic: the chain's fit, the effects asked for that the points do not determine and the
    priors used (each with why), the worms' periodic error, the measurement sensor's fit."""

    chain: ChainFitStats
    undetermined_effects: dict[str, str]
    priors: dict[str, str]
    periodic_error: dict[str, dict[str, float]]
    meas: MeasFitStats


class FitInfo(TurntableFit, ScaleFit, RotationFit, HomographyFit, AxisTransformFit, KinematicFit):
    """MODEL.json `fit`: the fit's statistics, each method's keys as its part above states them
    (JSON-serialisable)."""


class CovarianceJSON(TypedDict):
    """MODEL.json `covariance`: the parameters' names in the matrix's order and the matrix (null
    where not finite)."""

    names: list[str]
    matrix: list[list[float | None]]


class ModelJSON(TypedDict):
    """MODEL.json as a model writes it (docs/model.schema.json); `provenance` where recorded."""

    format_version: int
    kind: str
    method: str
    columns: list[str]
    parameters: dict[str, ParameterJSON]
    covariance: CovarianceJSON | None
    residuals: ResidualSummary
    fit: FitInfo
    notes: list[str]
    options: ModelOptions
    state: ModelState
    provenance: NotRequired[dict[str, object]]


@dataclass
class Parameter:
    value: float
    unit: str
    fixed: bool = False  # held at this value, not fitted (the data cannot separate it)
    note: str = ""

    def to_dict(self) -> ParameterJSON:
        entry: ParameterJSON = {"value": _num(self.value), "unit": self.unit}
        if self.fixed:
            entry["fixed"] = True
        if self.note:
            entry["note"] = self.note
        return entry


@dataclass
class CalibrationModel:
    kind: str
    method: str
    columns: list[str]
    parameters: dict[str, Parameter]
    covariance_names: list[str] = field(default_factory=list)
    covariance: NDArray[np.float64] | None = None
    # {"unit": ..., "columns": {col: {"rms": .., "max_abs": .., "values": [..]}}}
    residuals: ResidualSummary = field(default_factory=lambda: ResidualSummary())
    fit: FitInfo = field(default_factory=lambda: FitInfo())  # n_points, dof, sigma, ...
    notes: list[str] = field(default_factory=list)
    state: ModelState = field(default_factory=lambda: ModelState())  # method-specific
    options: ModelOptions = field(default_factory=lambda: ModelOptions())
    # version, UTC time, command, inputs' SHA-256 (service.io.provenance's record)
    provenance: Mapping[str, object] = field(default_factory=dict)

    # --- parameter access -------------------------------------------------------------
    def value(self, name: str) -> float:
        return float(self.parameters[name].value)

    def values(self, names: Sequence[str]) -> NDArray[np.float64]:
        return np.array([self.value(n) for n in names], dtype=float)

    def cov_of(self, names: Sequence[str]) -> NDArray[np.float64] | None:
        """Covariance sub-matrix for `names` (zero rows for fixed / unlisted parameters)."""
        if self.covariance is None:
            return None
        idx = {n: i for i, n in enumerate(self.covariance_names)}
        out = np.zeros((len(names), len(names)))
        listed = [(position, idx[n]) for position, n in enumerate(names) if n in idx]
        if listed:
            at, src = np.array(listed).T
            out[at[:, None], at] = np.asarray(self.covariance)[src[:, None], src]
        return out

    def std(self, name: str) -> float | None:
        if self.covariance is None or name not in self.covariance_names:
            return None
        i = self.covariance_names.index(name)
        return float(math.sqrt(max(self.covariance[i, i], 0.0)))

    # --- JSON -------------------------------------------------------------------------
    def to_json_dict(self) -> ModelJSON:
        doc: ModelJSON = {
            "format_version": FORMAT_VERSION,
            "kind": self.kind,
            "method": self.method,
            "columns": list(self.columns),
            "parameters": {k: param.to_dict() for k, param in self.parameters.items()},
            "covariance": None,
            "residuals": _jsonable(self.residuals),
            "fit": _jsonable(self.fit),
            "notes": list(self.notes),
            "options": _jsonable(self.options),
            "state": _jsonable(self.state),
        }
        if self.covariance is not None:
            doc["covariance"] = {
                "names": list(self.covariance_names),
                "matrix": [[_num(value) for value in row] for row in np.asarray(self.covariance)],
            }
        if self.provenance:
            doc["provenance"] = _jsonable(self.provenance)
        return doc

    @classmethod
    def from_json_dict(cls, d: Any, source: str = "model") -> CalibrationModel:
        _check_required_fields(d, source)
        _check_optional_fields(d, source)
        params = _parameters_of(d["parameters"], source)
        names, matrix = _covariance_of(d.get("covariance"), params, source)
        # checked to be JSON objects above; their keys are the method's
        residuals: ResidualSummary = d.get("residuals") or ResidualSummary()
        state: ModelState = d.get("state") or ModelState()
        options: ModelOptions = d.get("options") or ModelOptions()
        fit: FitInfo = d.get("fit") or FitInfo()
        return cls(
            kind=str(d["kind"]),
            method=str(d["method"]),
            columns=list(d["columns"]),
            parameters=params,
            covariance_names=names,
            covariance=matrix,
            residuals=residuals,
            fit=fit,
            notes=list(d.get("notes") or []),
            state=state,
            options=options,
            provenance=d.get("provenance") or {},
        )


def _check_required_fields(doc: Any, source: str) -> None:
    """Refuse a document that lacks what every model has (named field by field)."""
    if not isinstance(doc, dict):
        raise InputError(f"{source}: a model is a JSON object")
    fv = doc.get("format_version")
    if fv != FORMAT_VERSION:
        raise InputError(
            f"{source}: field format_version: {fv!r} is not supported (expected {FORMAT_VERSION})"
        )
    for key in ("kind", "method", "columns", "parameters"):
        if key not in doc:
            raise InputError(f"{source}: field {key}: missing required field")
    for key in ("kind", "method"):
        if not isinstance(doc[key], str):
            raise InputError(f"{source}: field {key}: must be a string")
    if not isinstance(doc["columns"], list) or not all(
        isinstance(column, str) for column in doc["columns"]
    ):
        raise InputError(f"{source}: field columns: must be a list of column names")


def _check_optional_fields(doc: Mapping[str, object], source: str) -> None:
    """Refuse an optional field of the wrong JSON type (an absent or null one is empty)."""
    for key, kind in (
        ("residuals", dict),
        ("fit", dict),
        ("state", dict),
        ("options", dict),
        ("notes", list),
        ("provenance", dict),
    ):
        if doc.get(key) is not None and not isinstance(doc[key], kind):
            raise InputError(
                f"{source}: field {key}: must be {'an object' if kind is dict else 'a list'}"
            )


def _parameters_of(entries: Any, source: str) -> dict[str, Parameter]:
    """The `parameters` object read back, each entry checked for a unit and a finite value."""
    params = {}
    if not isinstance(entries, dict):
        raise InputError(f"{source}: field parameters: must be an object")
    for name, entry in entries.items():
        if not isinstance(entry, dict) or "value" not in entry or "unit" not in entry:
            raise InputError(f"{source}: field parameters.{name}: needs value and unit")
        value = entry["value"]
        if (
            not isinstance(value, (int, float))
            or isinstance(value, bool)
            or not math.isfinite(float(value))
        ):
            raise InputError(
                f"{source}: field parameters.{name}.value: {value!r} is not a finite number"
            )
        params[name] = Parameter(
            float(value),
            str(entry["unit"]),
            bool(entry.get("fixed", False)),
            str(entry.get("note", "")),
        )
    return params


def _covariance_of(
    cov: Any, params: dict[str, Parameter], source: str
) -> tuple[list[str], NDArray[np.float64] | None]:
    """The `covariance` object as (names, matrix), its names checked against the parameters."""
    if cov is None:
        return [], None
    try:
        names = [str(n) for n in cov["names"]]
        matrix = np.array(cov["matrix"], dtype=float)
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{source}: field covariance: needs names and a numeric matrix") from None
    if matrix.shape != (len(names), len(names)) or not np.all(np.isfinite(matrix)):
        raise InputError(
            f"{source}: field covariance.matrix: must be a finite {len(names)}x{len(names)} matrix"
        )
    unknown = [n for n in names if n not in params]
    if unknown:
        raise InputError(f"{source}: field covariance.names: {unknown[0]!r} is not a parameter")
    return names, matrix


def _num(v: float | np.floating) -> float | None:
    number = float(v)
    return number if math.isfinite(number) else None


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(item) for k, item in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(item) for item in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return _num(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def table_tilt_range(columns: Mapping[str, NDArray[np.float64]]) -> dict[str, list[float]] | None:
    """The table tilts a stage model was fitted on: per axis [min, max] of the reference sensor's
    readings (the frame the model corrects to), as MODEL.json `fit.table_tilt_range_deg` keeps them;
    None without them."""
    out: dict[str, list[float]] = {}
    for axis in "xy":
        values = np.asarray(columns.get(f"ref_{axis}_deg", []), dtype=float)
        values = values[np.isfinite(values)]
        if values.size == 0:
            return None
        out[axis] = [float(values.min()), float(values.max())]
    return out


def stored_table_tilt_range(model: CalibrationModel) -> dict[str, list[float]] | None:
    """MODEL.json `fit.table_tilt_range_deg` when it is there and well formed (older models do not
    have it)."""
    return stored_range(model.fit.get("table_tilt_range_deg"))


def stored_range(seen: Any) -> dict[str, list[float]] | None:
    """A stated `table_tilt_range_deg` ({"x": [min, max], "y": [min, max]}) when well formed, else
    None."""
    if not isinstance(seen, dict):
        return None
    out = {}
    for axis in "xy":
        pair = seen.get(axis)
        if not (
            isinstance(pair, list)
            and len(pair) == 2
            and all(isinstance(bound, int | float) for bound in pair)
        ):
            return None
        out[axis] = [float(pair[0]), float(pair[1])]
    return out


def residual_summary(
    residuals: dict[str, NDArray[np.float64]], unit: str, keep_values: bool = True
) -> ResidualSummary:
    """RMS, max |r| (and the values) of each residual column: what every model reports."""
    cols = {}
    for name, values in residuals.items():
        values = np.asarray(values, dtype=float)
        entry: ResidualColumn = {
            "rms": float(np.sqrt(np.mean(values**2))) if values.size else 0.0,
            "max_abs": float(np.max(np.abs(values))) if values.size else 0.0,
        }
        if keep_values:
            entry["values"] = values.tolist()
        cols[name] = entry
    return {"unit": unit, "columns": cols}
