"""The results a certificate states of one record: the item's parameters with their covariance, the
calibrated range and points, the validation table, the uncertainty budget and the temperature.

Pure: maps what the record keeps (MODEL.json, validation, budget, the calibration points) to
`dcc` values. Every uncertainty is expanded for 95 % with k from Student's t at the degrees of
freedom it has (the fit's, or the Welch-Satterthwaite effective ones of a budget), and says so.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import Literal, NamedTuple, cast

import numpy as np
from numpy.typing import NDArray
from scipy import special

from service.calibration.budget import (
    BudgetResult,
    Component,
    TemperatureStats,
    UncertaintyBudget,
    combine,
    model_dof,
    reading_components,
)
from service.calibration.uncertainty import COVERAGE, coverage_factor, dof_of_coverage_factor
from service.lims import dcc
from service.lims.as_found import AXES, AxisAsFound, MeasuredPoint, Uncertain
from service.lims.facts import (
    AmbientCondition,
    CalibrationPoint,
    ModelDocument,
    ModelParameter,
    RecordConditions,
    RecordFacts,
    StatedRange,
    Validation,
    ValidationPoint,
)


class CertificateRefused(ValueError):
    """The record cannot be certified as it stands (the message says what is missing)."""


def distribution(dof: float) -> str:
    return "student-t" if math.isfinite(dof) else "normal"


def _dof_text(dof: float | None) -> str:
    return (
        "infinite degrees of freedom (normal)"
        if dof is None or not math.isfinite(dof)
        else f"{dof:.0f} degrees of freedom"
    )


def bench_parameters(model: ModelDocument) -> set[str]:
    """The parameters that describe the bench (stage scales, desk tilt, the reference's mounting),
    not the item."""
    return set((model.get("state") or {}).get("chain_parameters") or [])


def region_factor(n: int, dof: float, probability: float = COVERAGE) -> float:
    """k of the joint n-dimensional coverage ellipsoid: √(n·F(n, ν; p)), √χ²(n; p) for infinite
    ν."""
    if math.isfinite(dof) and dof > 0:
        return float(math.sqrt(n * special.fdtri(n, dof, probability)))
    return float(math.sqrt(special.chdtri(n, 1.0 - probability)))


class _Fit(NamedTuple):
    """What the fit states of the parameters: its covariance (names and matrix), its degrees of
    freedom and their coverage factor."""

    names: list[str]
    matrix: NDArray[np.float64]
    dof: float
    k: float


def _fit_of(model: ModelDocument, probability: float) -> _Fit:
    """The fit's covariance, symmetrised, with its degrees of freedom and k (no names without a
    covariance)."""
    cov = model.get("covariance") or None
    names: list[str] = list(cov["names"]) if cov else []
    matrix = np.asarray(cov["matrix"], dtype=float) if cov else np.zeros((0, 0))
    # a covariance is symmetric; a fit's rounding leaves ~1e-16 between halves
    matrix = (matrix + matrix.T) / 2.0
    nu = model_dof(model)
    return _Fit(names, matrix, nu, float(coverage_factor(nu, probability)))


def _parameter_value(
    name: str,
    param: ModelParameter,
    from_budget: Mapping[str, BudgetResult],
    fit: _Fit,
    probability: float,
) -> tuple[dcc.Value, bool]:
    """One parameter as the certificate states it, and whether it is one of the fitted vector: held
    fixed, with the budget's U and k, with the fit's, or bare when neither states its
    uncertainty."""
    note = str(param.get("note") or "")
    unit = str(param["unit"])
    if param.get("fixed"):
        value = dcc.Value(
            name, f"{name} (held fixed, not fitted)", float(param["value"]), unit, note=note
        )
        return value, False
    if name in from_budget:
        entry = from_budget[name]
        why = (
            "U = k·u with u from the fit's covariance and the reference standard (u = U/k of "
            "its certificate); "
            f"k from Student's t at {_dof_text(entry['dof_eff'])} (Welch-Satterthwaite)"
        )
        value = dcc.Value(
            name,
            name,
            float(param["value"]),
            unit,
            float(entry["expanded_uncertainty"]),
            float(entry["coverage_factor"]),
            probability,
            "; ".join(filter(None, [why, note])),
            distribution(entry["dof_eff"] or math.inf),
        )
        return value, True
    if name in fit.names:
        index = fit.names.index(name)
        u_fit = math.sqrt(max(float(fit.matrix[index, index]), 0.0))
        why = (
            "U = k·u with u from the fit's covariance; k from Student's t at "
            f"{_dof_text(fit.dof)} (the fit's)"
        )
        value = dcc.Value(
            name,
            name,
            float(param["value"]),
            unit,
            u_fit * fit.k,
            fit.k,
            probability,
            "; ".join(filter(None, [why, note])),
            distribution(fit.dof),
        )
        return value, True
    return dcc.Value(name, name, float(param["value"]), unit, note=note), False


def _parameter_covariance(
    fitted: Sequence[str],
    params: Mapping[str, ModelParameter],
    from_budget: Mapping[str, BudgetResult],
    fit: _Fit,
    probability: float,
) -> dcc.Covariance:
    """The fitted parameters as one vector with their covariance, a budget's parameter with the
    standard's variance on the diagonal and the budget's k."""
    idx = [fit.names.index(name) for name in fitted]
    sub = fit.matrix[np.ix_(idx, idx)].copy()
    ks = []
    for i, name in enumerate(fitted):
        if name in from_budget:
            entry = from_budget[name]
            # the standard's variance added on the diagonal (independent)
            sub[i, i] = (float(entry["standard_uncertainty"])) ** 2
            ks.append(float(entry["coverage_factor"]))
        else:
            ks.append(fit.k)
    return dcc.Covariance(
        labels=tuple(fitted),
        values=tuple(float(params[name]["value"]) for name in fitted),
        units=tuple(str(params[name]["unit"]) for name in fitted),
        matrix=tuple(tuple(float(x) for x in row) for row in sub),
        k=tuple(ks),
        probability=probability,
        region_k=region_factor(len(fitted), fit.dof, probability),
        distribution=distribution(fit.dof),
        note=f"Covariance of the fitted parameters (the fit's, {_dof_text(fit.dof)}), in the "
        "products of their units, columns in the order of the labels; a zero offset's "
        "variance includes the reference standard's. The joint coverage factor is that of "
        "the hyper-ellipsoid for the stated probability.",
    )


def _parameters_description(left_out: Sequence[str]) -> str:
    """What the parameters are, naming the bench's own that were fitted with them but are not
    stated."""
    description = (
        "Parameters of the item's model fitted by least squares, with their expanded "
        "uncertainties and their covariance matrix."
    )
    if left_out:
        description += (
            f" The bench's own {len(left_out)} parameters ({', '.join(left_out[:4])}"
            f"{', ...' if len(left_out) > 4 else ''}) were fitted with them; they describe the "
            "measuring "
            "set-up, not the item, and are kept in the calibration record, not stated here."
        )
    return description


def parameter_result(
    model: ModelDocument, budget: UncertaintyBudget | None, probability: float = COVERAGE
) -> dcc.Result:
    """The item's parameters with expanded uncertainties, and as one vector with their covariance.

    A parameter the budget lists (a zero offset, which carries the reference's angle scale) takes
    the budget's U and k (the standard's u = U/k included, and in the covariance's diagonal too).
    """
    params = model.get("parameters") or {}
    bench = bench_parameters(model)
    fit = _fit_of(model, probability)
    from_budget = {entry["quantity"]: entry for entry in _results_of(budget)}
    values: list[dcc.Value] = []
    fitted: list[str] = []
    for name, param in params.items():
        if name in bench:
            continue
        value, in_vector = _parameter_value(name, param, from_budget, fit, probability)
        values.append(value)
        if in_vector:
            fitted.append(name)
    if not values:
        raise CertificateRefused("the record's model has no parameters")
    covariance = (
        _parameter_covariance(fitted, params, from_budget, fit, probability) if fitted else None
    )
    return dcc.Result(
        "Calibration parameters",
        _parameters_description(sorted(bench & set(params))),
        values=tuple(values),
        covariance=covariance,
    )


def _quantities(points: Sequence[ValidationPoint]) -> list[tuple[str, str]]:
    """(quantity, unit) pairs that every validation point gives as reference_<q>_<unit> and
    measured_<q>_<unit>."""
    first = points[0]
    out = []
    for key in first:
        if key.startswith("reference_"):
            rest = key.removeprefix("reference_")
            quantity, _, unit = rest.rpartition("_")
            if quantity and f"measured_{rest}" in first:
                out.append((quantity, unit))
    return out


def _validation_summary(validation: Validation) -> list[dcc.Value]:
    """The validation's summary figures it states: RMS and largest |error|, number of points."""
    summary = []
    figures: tuple[tuple[Literal["rms_deg", "max_deg"], str], ...] = (
        ("rms_deg", "RMS of the errors"),
        ("max_deg", "largest |error|"),
    )
    for key, name in figures:
        figure = validation.get(key)
        if isinstance(figure, int | float):
            summary.append(dcc.Value(key, name, float(figure), "deg", ref_type="tiltlab_summary"))
    n_points = validation.get("n_points")
    if isinstance(n_points, int):
        summary.append(
            dcc.Value(
                "n_points",
                "validation points",
                float(n_points),
                "1",
                ref_type="tiltlab_summary",
            )
        )
    return summary


def _stated_uncertainty(
    points: Sequence[ValidationPoint],
    quantity: str,
    unit: str,
    validation: Validation,
    k_bound: float | None,
) -> tuple[tuple[float, ...] | None, tuple[float, ...] | None]:
    """Each point's U of the measured value and its k as the points state them (None unless every
    point gives U); a missing k is the bound, refused without one."""
    ukey = f"u_{quantity}_{unit}"
    if not all(isinstance(point.get(ukey), int | float) for point in points):
        return None, None
    expanded_u = tuple(float(point[ukey]) for point in points)
    stated = [point.get(f"k_{quantity}", point.get("k", validation.get("k"))) for point in points]
    if any(k is None for k in stated) and k_bound is None:
        raise CertificateRefused(f"validation points give {ukey} without its coverage factor")
    # a missing k falls back to the bound, which the refusal above guarantees is there
    ks = tuple(float(k) if k is not None else float(cast(float, k_bound)) for k in stated)
    return expanded_u, ks


def _with_budget(
    expanded_u: tuple[float, ...],
    ks: tuple[float, ...],
    others: Sequence[Component],
    probability: float,
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Each point's U and k once the fit's part is combined with the budget's other components."""
    k_arr = np.asarray(ks)
    combined = combine(
        np.asarray(expanded_u) / k_arr,
        dof_of_coverage_factor(k_arr, probability),
        others,
        probability,
    )
    return tuple(float(x) for x in combined.U), tuple(float(x) for x in combined.k)


def _validation_columns(
    points: Sequence[ValidationPoint],
    quantity: str,
    unit: str,
    validation: Validation,
    k_bound: float | None,
    others: Sequence[Component],
    probability: float,
) -> list[dcc.Column]:
    """One quantity's reference, measured and error columns, the last two with each point's U."""
    ref = tuple(float(point[f"reference_{quantity}_{unit}"]) for point in points)
    meas = tuple(float(point[f"measured_{quantity}_{unit}"]) for point in points)
    err = tuple(measured - reference for measured, reference in zip(meas, ref, strict=True))
    expanded_u, ks = _stated_uncertainty(points, quantity, unit, validation, k_bound)
    has_u = expanded_u is not None
    if expanded_u is not None and ks is not None and others and unit == "deg":
        expanded_u, ks = _with_budget(expanded_u, ks, others, probability)
    dist = "student-t" if has_u else None
    stated_probability = probability if has_u else None
    return [
        dcc.Column(
            f"reference_{quantity}_{unit}",
            f"reference {quantity}",
            ref,
            unit,
            ref_type="basic_referenceValue",
        ),
        dcc.Column(
            f"measured_{quantity}_{unit}",
            f"measured {quantity} (corrected)",
            meas,
            unit,
            expanded_u,
            ks,
            stated_probability,
            ref_type="basic_measuredValue",
            distribution=dist,
        ),
        dcc.Column(
            f"error_{quantity}_{unit}",
            f"error {quantity} (measured − reference)",
            err,
            unit,
            expanded_u,
            ks,
            stated_probability,
            ref_type="basic_measurementError",
            distribution=dist,
        ),
    ]


def _validation_description(others: Sequence[Component], k_bound: float | None) -> str:
    """How the validation's errors and their uncertainties were obtained."""
    return (
        "Each validation point was measured after the fit and corrected with the fitted "
        "parameters; the error is the corrected reading minus the reference. The uncertainty of "
        "the error is that of the corrected reading: GUM propagation of the parameters' "
        "covariance and the reading noise"
        + (
            ", combined with the uncertainty budget's other components (reference standards, "
            "resolution, temperature)"
            if others
            else ""
        )
        + "; k is Student's t at each point's effective degrees of freedom (Welch-Satterthwaite)"
        + (
            "; where a point does not state its own coverage factor, the one shown is Student's t "
            "at the fit's "
            "degrees of freedom, an upper bound of it, and U covers the stated probability."
            if k_bound
            else "."
        )
    )


def validation_result(
    validation: Validation,
    probability: float = COVERAGE,
    k_bound: float | None = None,
    budget: UncertaintyBudget | None = None,
) -> dcc.Result | None:
    """The validation table (reference, measured, error, each with its expanded uncertainty) and its
    summary.

    Reads `validation["points"]`: one row per validation point with `reference_<q>_<unit>`,
    `measured_<q>_<unit>`, optionally `u_<q>_<unit>` (expanded uncertainty of the measured value
    from the fit) and `k_<q>` or `k` (its coverage factor). The error is measured − reference. With
    a budget, each point's U combines the fit's part with the budget's (standards, resolution,
    temperature).
    """
    summary = _validation_summary(validation)
    points = validation.get("points") or []
    if isinstance(validation.get("coverage_probability"), int | float):
        probability = float(validation["coverage_probability"])
    others = reading_components(budget)
    columns: list[dcc.Column] = []
    if points:
        quantities = _quantities(points)
        if not quantities:
            raise CertificateRefused(
                "validation points name no reference_<quantity>_<unit>/measured_... pair"
            )
        for quantity, unit in quantities:
            columns += _validation_columns(
                points, quantity, unit, validation, k_bound, others, probability
            )
    if not summary and not columns:
        return None
    return dcc.Result(
        "Validation on points not used in the fit",
        _validation_description(others, k_bound),
        values=tuple(summary),
        columns=tuple(columns),
        table_ref_type="tiltlab_validationPoint",
    )


def calibration_points_result(
    points: Sequence[CalibrationPoint], stated_range: StatedRange | None = None
) -> dcc.Result | None:
    """The calibrated range (stated by the record, else the points' extremes of each reference
    quantity) and the calibration points themselves: one column per `<quantity>_<unit>` key of the
    points."""
    if not points:
        return None
    keys = [
        key
        for key in points[0]
        if "_" in key and all(isinstance(point.get(key), int | float) for point in points)
    ]
    columns = []
    for key in keys:
        quantity, _, unit = key.rpartition("_")
        columns.append(
            dcc.Column(
                key,
                quantity.replace("_", " "),
                tuple(float(point[key]) for point in points),
                unit,
                ref_type="tiltlab_calibrationPoint",
            )
        )
    ranges = _ranges(stated_range) or _column_ranges(columns)
    return dcc.Result(
        "Calibrated range and calibration points",
        f"The {len(points)} points the model was fitted on: the reference's value and the item's "
        "indication at each. The results hold within the range of the reference values.",
        values=tuple(_range_values(ranges)),
        columns=tuple(columns),
        table_ref_type="tiltlab_calibrationPoint",
    )


def _ranges(stated_range: StatedRange | None) -> dict[str, tuple[float, float]]:
    ranges: dict[str, tuple[float, float]] = {}
    for key, span in (stated_range or {}).items():
        if isinstance(span, list | tuple) and len(span) == 2 and "_" in key:
            ranges[f"reference_{key}"] = (float(span[0]), float(span[1]))
    return ranges


def _column_ranges(columns: Sequence[dcc.Column]) -> dict[str, tuple[float, float]]:
    """The extremes of each reference column: the calibrated range where the record states none."""
    return {
        column.label: (min(column.values), max(column.values))
        for column in columns
        if column.label.startswith("reference_")
    }


def _range_values(ranges: Mapping[str, tuple[float, float]]) -> list[dcc.Value]:
    values = []
    for label, (lo, hi) in ranges.items():
        quantity, _, unit = label.rpartition("_")
        name = quantity.replace("_", " ")
        values += [
            dcc.Value(
                f"{label}_min", f"lowest {name}", lo, unit, ref_type="tiltlab_calibratedRange"
            ),
            dcc.Value(
                f"{label}_max", f"highest {name}", hi, unit, ref_type="tiltlab_calibratedRange"
            ),
        ]
    return values


def _uncertain_column(
    label: str, name: str, q: Uncertain, ref_type: str, probability: float = COVERAGE
) -> dcc.Column:
    return dcc.Column(
        label,
        name,
        tuple(float(value) for value in q.value),
        "deg",
        tuple(float(x) for x in q.expanded_u),
        tuple(float(k) for k in q.k),
        probability,
        ref_type=ref_type,
        distribution="student-t" if bool(np.all(np.isfinite(q.dof))) else "normal",
    )


def stage_points_result(
    points: Sequence[MeasuredPoint],
    found: Mapping[str, AxisAsFound],
    stated_range: StatedRange | None = None,
) -> dcc.Result | None:
    """The calibrated range and the calibration points of a stage record: at each point the model
    was fitted on, the reference's value and the item's indication, each with its expanded
    uncertainty."""
    fitted = [i for i, point in enumerate(points) if point.fitted]
    if not fitted:
        return None
    cols = []
    for axis in AXES:
        axis_found = found[axis]
        ref = Uncertain(
            axis_found.reference.value[fitted],
            axis_found.reference.u[fitted],
            axis_found.reference.dof[fitted],
            axis_found.reference.k[fitted],
        )
        cols += [
            _uncertain_column(
                f"reference_{axis}_deg", f"reference {axis}", ref, "tiltlab_calibrationPoint"
            ),
            dcc.Column(
                f"indication_{axis}_deg",
                f"indication {axis}",
                tuple(float(value) for value in axis_found.indication.value[fitted]),
                "deg",
                ref_type="tiltlab_calibrationPoint",
            ),
        ]
    ranges = _ranges(stated_range) or _column_ranges(cols)
    return dcc.Result(
        "Calibrated range and calibration points",
        f"The {len(fitted)} points the model was fitted on: the reference's value, with its "
        "expanded uncertainty, and the item's indication at each, each the mean of the readings "
        "taken after the table settled (the indication is written to the decimal place of the "
        "reference's U). The reference value's expanded uncertainty combines the reference "
        "standards' (u = U/k of their certificates), the reference sensor's resolution and the "
        "noise of its mean; the indication's own (the item's resolution and the noise of its "
        "mean) is part of the indication error's, stated with the indication errors. The "
        "results hold within the range of the reference values.",
        values=tuple(_range_values(ranges)),
        columns=tuple(cols),
        table_ref_type="tiltlab_calibrationPoint",
    )


def indication_error_result(
    points: Sequence[MeasuredPoint], found: Mapping[str, AxisAsFound]
) -> dcc.Result | None:
    """The item's indication error as found (before any correction) at every calibration and
    validation point."""
    if not points:
        return None
    cols: list[dcc.Column] = []
    for axis in AXES:
        cols.append(
            _uncertain_column(
                f"indication_error_{axis}_deg",
                f"indication error {axis} (indication − reference)",
                found[axis].error,
                "tiltlab_indicationError",
            )
        )
    for axis in AXES:
        cols += [
            dcc.Column(
                f"reference_{axis}_deg",
                f"reference {axis}",
                tuple(float(value) for value in found[axis].reference.value),
                "deg",
                ref_type="tiltlab_indicationError",
            ),
            dcc.Column(
                f"indication_{axis}_deg",
                f"indication {axis}",
                tuple(float(value) for value in found[axis].indication.value),
                "deg",
                ref_type="tiltlab_indicationError",
            ),
        ]
    n_fit = sum(point.fitted for point in points)
    largest = {axis: float(np.max(np.abs(found[axis].error.value))) for axis in AXES}
    values = tuple(
        dcc.Value(
            f"largest_indication_error_{axis}_deg",
            f"largest |indication error| {axis}",
            largest[axis],
            "deg",
            ref_type="tiltlab_summary",
        )
        for axis in AXES
    )
    return dcc.Result(
        "Indication error as found",
        f"The item's reading minus the reference's at each of the {len(points)} measured points, "
        f"before any correction: rows 1 to {n_fit} are the calibration points, the rest the "
        "validation points, in the order they were measured. The error's expanded uncertainty "
        "combines the reference value's (reference standards, the reference sensor's resolution "
        "and the noise of its mean) with the indication's (the item's resolution and the noise "
        "of its mean); k is Student's t at each point's Welch-Satterthwaite degrees of freedom. "
        "Statements of conformity rest on these errors.",
        values=values,
        columns=tuple(cols),
        table_ref_type="tiltlab_indicationError",
    )


def _two_digits(u: float) -> float:
    return float(f"{u:.2g}")


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_")


NOT_TRACEABLE = "no reference standard: not traceable"
_COMBINATION = "tiltlab_uncertaintyCombination"


def _component_values(entry: BudgetResult) -> list[dcc.Value]:
    """One result's components, each its standard uncertainty (labelled by source, and by name
    where a source gives several)."""
    unit, quantity = str(entry["unit"]), str(entry["quantity"])
    sources = [contribution["source"] for contribution in entry["contributions"]]
    values = []
    for contribution in entry["contributions"]:
        what = (
            "the fit (parameters' covariance and reading noise)"
            if contribution["source"] == "fit"
            else str(contribution["name"])
        )
        label = f"standard_uncertainty_{quantity}_{contribution['source']}"
        if sources.count(contribution["source"]) > 1:
            label += "_" + _slug(str(contribution.get("name") or ""))
        values.append(
            dcc.Value(
                label,
                f"{entry['name']}: standard uncertainty from {what}",
                _two_digits(contribution["standard_uncertainty"]),
                unit,
                note=_dof_text(contribution.get("dof")),
                ref_type="tiltlab_uncertaintyComponent",
            )
        )
    return values


def _combination_values(entry: BudgetResult) -> list[dcc.Value]:
    """One result's combination: u_c, k and U = k·u_c."""
    unit, quantity = str(entry["unit"]), str(entry["quantity"])
    dof = entry.get("dof_eff")
    return [
        dcc.Value(
            f"combined_standard_uncertainty_{quantity}",
            f"{entry['name']}: combined standard uncertainty u_c",
            _two_digits(entry["standard_uncertainty"]),
            unit,
            note=f"root sum of squares of the components; {_dof_text(dof)}"
            + (" (Welch-Satterthwaite)" if dof is not None else ""),
            ref_type=_COMBINATION,
        ),
        dcc.Value(
            f"coverage_factor_{quantity}",
            f"{entry['name']}: coverage factor k",
            float(entry["coverage_factor"]),
            "1",
            note=f"Student's t at {_dof_text(dof)} for {float(entry['coverage_probability']):.0%}",
            ref_type=_COMBINATION,
        ),
        dcc.Value(
            f"expanded_uncertainty_{quantity}",
            f"{entry['name']}: expanded uncertainty U = k·u_c",
            _two_digits(entry["expanded_uncertainty"]),
            unit,
            note=f"coverage probability {float(entry['coverage_probability']):g}",
            ref_type=_COMBINATION,
        ),
    ]


def _single_reading_value(
    entry: BudgetResult, readings_per_point: int, s_one: float, nu_one: float
) -> dcc.Value:
    """A corrected tilt's U for a single reading: u_c with one reading's noise beyond that of the
    mean the calibration points took, Welch-Satterthwaite degrees of freedom."""
    unit, quantity = str(entry["unit"]), str(entry["quantity"])
    dof = entry.get("dof_eff")
    # one reading's noise beyond that of the mean
    extra = s_one**2 * (1.0 - 1.0 / readings_per_point)
    u_single = math.sqrt(float(entry["standard_uncertainty"]) ** 2 + extra)
    denom = (float(entry["standard_uncertainty"]) ** 4 / dof if dof else 0.0) + extra**2 / nu_one
    nu_single = u_single**4 / denom if denom > 0 else math.inf
    k_single = float(coverage_factor(nu_single, float(entry["coverage_probability"])))
    return dcc.Value(
        f"expanded_uncertainty_{quantity}_single_reading",
        f"{entry['name']}: expanded uncertainty U of a single corrected reading",
        _two_digits(k_single * u_single),
        unit,
        note=(
            "u_c combined with one reading's noise beyond that of a mean of "
            f"{readings_per_point} (s = {_two_digits(s_one):g} {unit} pooled over "
            f"the points, {nu_one:.0f} degrees of freedom): k = {k_single:.3g} at "
            f"{_dof_text(nu_single)}"
        ),
        ref_type=_COMBINATION,
    )


def _budget_description(readings_per_point: int | None, traceable: bool) -> str:
    """How the budget combines its components, what the corrected tilt's U holds for, and a warning
    when no reference standard is in it."""
    held = (
        "The expanded uncertainty of the corrected table tilt holds for a corrected value that "
        f"is the mean of {readings_per_point} readings taken after the table settled, as at each "
        "calibration point; a single reading has more noise, and its expanded uncertainty is "
        "stated beside it where the points give the readings' spread. "
        if readings_per_point
        else ""
    )
    return (
        held + "Each result's standard uncertainty components (GUM): the fit, each reference "
        "standard (u = U/k of its certificate; the result is on the reference's angle scale), "
        "the sensors' resolution (r/√12) and, where the temperature varied, its influence; "
        "combined by root sum of squares into the combined standard uncertainty u_c; the "
        "expanded uncertainty U = k·u_c, with k from Student's t at the Welch-Satterthwaite "
        "effective degrees of freedom (components that rest on one fit's estimated standard "
        "deviation count as one, with that fit's degrees of freedom)."
        + (
            ""
            if traceable
            else f" Warning: {NOT_TRACEABLE}: no reference standard's uncertainty is in this "
            "budget."
        )
    )


def _results_of(budget: UncertaintyBudget | None) -> list[BudgetResult]:
    """The budget's results (none without a budget)."""
    return (budget.get("results") if budget else None) or []


def _has_reference_standard(entries: Sequence[BudgetResult]) -> bool:
    """Whether a reference standard's uncertainty is in the budget: without one the result is not
    traceable."""
    return any(
        contribution.get("source") == "reference_standard"
        for entry in entries
        for contribution in entry["contributions"]
    )


def budget_result(
    budget: UncertaintyBudget | None,
    readings_per_point: int | None = None,
    single_reading: Mapping[str, tuple[float, float]] | None = None,
) -> dcc.Result | None:
    """The uncertainty budget (GUM): for each result, each component's standard uncertainty and the
    combination.

    `readings_per_point`: how many readings each calibration point's mean took; the corrected tilt's
    U holds for such a mean. `single_reading`: the item's noise of one reading per axis (s, degrees
    of freedom), which gives the U of a single corrected reading beside it.
    """
    entries = _results_of(budget)
    if not entries:
        return None
    values: list[dcc.Value] = []
    traceable = _has_reference_standard(entries)
    for entry in entries:
        values += _component_values(entry)
        values += _combination_values(entry)
        quantity = str(entry["quantity"])
        axis = quantity.removeprefix("tilt_").removesuffix("_deg")
        if (
            quantity.startswith("tilt_")
            and readings_per_point
            and single_reading
            and axis in single_reading
        ):
            s_one, nu_one = single_reading[axis]
            values.append(_single_reading_value(entry, readings_per_point, s_one, nu_one))
    return dcc.Result(
        "Uncertainty budget",
        _budget_description(readings_per_point, traceable),
        values=tuple(values),
    )


def temperature_condition(
    record: RecordFacts, budget: UncertaintyBudget | None
) -> dcc.Condition | None:
    """The measurement sensor's internal temperature: its mean, with the range it lay in as a
    rectangular U."""
    t: TemperatureStats = (budget.get("temperature") if budget else None) or {}
    mean = (
        record.get("temp_c") if isinstance(record.get("temp_c"), int | float) else t.get("mean_c")
    )
    if not isinstance(mean, int | float):
        return None
    lo, hi = t.get("min_c", mean), t.get("max_c", mean)
    # at least half the reported 0.01 °C digit
    half = max(float(hi) - mean, mean - float(lo), 0.005)
    values = [
        dcc.Value(
            "temperature_mean",
            "mean",
            float(mean),
            "degC",
            half,
            math.sqrt(3.0),
            1.0,
            "the range the readings lay in (rectangular, its half-width as U)",
            "rectangular",
            ref_type="tiltlab_internalTemperature",
        )
    ]
    if "min_c" in t:
        values += [
            dcc.Value(
                "temperature_min",
                "lowest",
                float(lo),
                "degC",
                ref_type="tiltlab_internalTemperature",
            ),
            dcc.Value(
                "temperature_max",
                "highest",
                float(hi),
                "degC",
                ref_type="tiltlab_internalTemperature",
            ),
        ]
    return dcc.Condition(
        "temperature",
        "internal temperature of the measurement sensor",
        tuple(values),
        "The instrument's own internal temperature as it reported it at the calibration points, "
        "not a calibrated "
        "thermometer's reading of the ambient air; its own error is not known and not included.",
    )


AMBIENT: tuple[
    tuple[Literal["ambient_temperature_c", "relative_humidity_pct"], str, str, str], ...
] = (
    ("ambient_temperature_c", "temperature", "degC", "ambient air temperature of the laboratory"),
    ("relative_humidity_pct", "humidity", "%", "relative humidity of the laboratory's air"),
)
AMBIENT_SOURCE = {
    "ambient_sensor": "read by the bench's ambient sensor at every point; the standard uncertainty "
    "combines the sensor's stated one with the range the readings lay in",
    "request": "as entered with the calibration request, with the standard uncertainty given there",
}


def _ambient_condition(
    key: str, label: str, unit: str, name: str, stated: AmbientCondition
) -> dcc.Condition:
    """One ambient condition as the record states it: its value or mean with its standard
    uncertainty, and the range the readings lay in where the bench's sensor read it."""
    stated_u = stated.get("standard_uncertainty")
    source = str(stated.get("source") or "request")
    values = [
        dcc.Value(
            f"{key.rsplit('_', 1)[0]}_mean",
            "mean" if source == "ambient_sensor" else "value",
            float(stated["value"]),
            unit,
            note=AMBIENT_SOURCE.get(source, source),
            distribution="normal",
            ref_type="tiltlab_ambientCondition",
            standard_u=float(stated_u) if isinstance(stated_u, int | float) else None,
        )
    ]
    for end in ("min", "max"):
        if isinstance(stated.get(end), int | float):
            values.append(
                dcc.Value(
                    f"{key.rsplit('_', 1)[0]}_{end}",
                    "lowest" if end == "min" else "highest",
                    float(stated[end]),
                    unit,
                    ref_type="tiltlab_ambientCondition",
                )
            )
    return dcc.Condition(
        label,
        name,
        tuple(values),
        f"The {name} during the calibration, {AMBIENT_SOURCE.get(source, source)}.",
        ref_type=f"basic_{label} tiltlab_ambientCondition",
    )


def ambient_conditions(conditions: RecordConditions | None) -> list[dcc.Condition]:
    """The laboratory's ambient temperature and relative humidity during the calibration, each with
    its standard uncertainty, where the record states them (from the bench's ambient sensor or the
    job request)."""
    out = []
    for key, label, unit, name in AMBIENT:
        stated = conditions.get(key) if conditions else None
        if not isinstance(stated, Mapping) or not isinstance(stated.get("value"), int | float):
            continue
        out.append(_ambient_condition(key, label, unit, name, stated))
    return out
