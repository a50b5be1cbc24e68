"""The results a certificate states of one record: the item's parameters with their covariance, the
calibrated range and points, the validation table, the uncertainty budget and the temperature.

Pure: maps what the record keeps (MODEL.json, validation, budget, the calibration points) to
`dcc` values. Every uncertainty is expanded for 95 % with k from Student's t at the degrees of
freedom it has (the fit's, or the Welch-Satterthwaite effective ones of a budget), and says so.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, cast

import numpy as np
from scipy import special

from service.calibration.budget import combine, model_dof, reading_components
from service.calibration.uncertainty import COVERAGE, coverage_factor, dof_of_coverage_factor
from service.lims import dcc


class CertificateRefused(ValueError):
    """The record cannot be certified as it stands (the message says what is missing)."""


def distribution(dof: float) -> str:
    return "student-t" if math.isfinite(dof) else "normal"


def _dof_text(dof: float | None) -> str:
    return "infinite degrees of freedom (normal)" if dof is None or not math.isfinite(dof) \
        else f"{dof:.0f} degrees of freedom"


def bench_parameters(model: Mapping[str, Any]) -> set[str]:
    """The parameters that describe the bench (stage scales, desk tilt, the reference's mounting), not the item."""
    return set((model.get("state") or {}).get("chain_parameters") or [])


def region_factor(n: int, dof: float, probability: float = COVERAGE) -> float:
    """k of the joint n-dimensional coverage ellipsoid: √(n·F(n, ν; p)), √χ²(n; p) for infinite ν."""
    if math.isfinite(dof) and dof > 0:
        return float(math.sqrt(n * special.fdtri(n, dof, probability)))
    return float(math.sqrt(special.chdtri(n, 1.0 - probability)))


def parameter_result(model: Mapping[str, Any], budget: Mapping[str, Any] | None,
                     probability: float = COVERAGE) -> dcc.Result:
    """The item's parameters with expanded uncertainties, and as one vector with their covariance.

    A parameter the budget lists (a zero offset, which carries the reference's angle scale) takes
    the budget's U and k (the standard's u = U/k included, and in the covariance's diagonal too).
    """
    params = model.get("parameters") or {}
    bench = bench_parameters(model)
    cov = model.get("covariance") or None
    names: list[str] = list(cov["names"]) if cov else []
    matrix = np.asarray(cov["matrix"], dtype=float) if cov else np.zeros((0, 0))
    nu = model_dof(model)
    k_fit = float(coverage_factor(nu, probability))
    from_budget = {r["quantity"]: r for r in (budget or {}).get("results") or []}
    values: list[dcc.Value] = []
    fitted: list[str] = []
    for name, p in params.items():
        if name in bench:
            continue
        note = str(p.get("note") or "")
        unit = str(p["unit"])
        if p.get("fixed"):
            values.append(dcc.Value(name, f"{name} (held fixed, not fitted)", float(p["value"]), unit, note=note))
        elif name in from_budget:
            b = from_budget[name]
            why = (f"U = k·u with u from the fit's covariance and the reference standard (u = U/k of its certificate); "
                   f"k from Student's t at {_dof_text(b['dof_eff'])} (Welch-Satterthwaite)")
            values.append(dcc.Value(name, name, float(p["value"]), unit, float(b["U"]), float(b["k"]), probability,
                                    "; ".join(filter(None, [why, note])), distribution(b["dof_eff"] or math.inf)))
            fitted.append(name)
        elif name in names:
            u = math.sqrt(max(float(matrix[names.index(name), names.index(name)]), 0.0))
            why = f"U = k·u with u from the fit's covariance; k from Student's t at {_dof_text(nu)} (the fit's)"
            values.append(dcc.Value(name, name, float(p["value"]), unit, u * k_fit, k_fit, probability,
                                    "; ".join(filter(None, [why, note])), distribution(nu)))
            fitted.append(name)
        else:
            values.append(dcc.Value(name, name, float(p["value"]), unit, note=note))
    if not values:
        raise CertificateRefused("the record's model has no parameters")
    covariance = None
    if fitted:
        idx = [names.index(n) for n in fitted]
        sub = matrix[np.ix_(idx, idx)].copy()
        ks = []
        for i, n in enumerate(fitted):
            if n in from_budget:
                b = from_budget[n]
                sub[i, i] = (float(b["u"])) ** 2  # the standard's variance added on the diagonal (independent)
                ks.append(float(b["k"]))
            else:
                ks.append(k_fit)
        covariance = dcc.Covariance(
            labels=tuple(fitted), values=tuple(float(params[n]["value"]) for n in fitted),
            units=tuple(str(params[n]["unit"]) for n in fitted), matrix=tuple(tuple(float(x) for x in r) for r in sub),
            k=tuple(ks), probability=probability, region_k=region_factor(len(fitted), nu, probability),
            distribution=distribution(nu),
            note=f"Covariance of the fitted parameters (the fit's, {_dof_text(nu)}), in the products of their units, "
                 "columns in the order of the labels; a zero offset's variance includes the reference standard's. "
                 "The joint coverage factor is that of the hyper-ellipsoid for the stated probability.",
        )  # fmt: skip
    left_out = sorted(bench & set(params))
    description = ("Parameters of the item's model fitted by least squares, with their expanded uncertainties and "
                   "their covariance matrix.")
    if left_out:
        description += (f" The bench's own {len(left_out)} parameters ({', '.join(left_out[:4])}"
                        f"{', ...' if len(left_out) > 4 else ''}) were fitted with them; they describe the measuring "
                        "set-up, not the item, and are kept in the calibration record, not stated here.")
    return dcc.Result("Calibration parameters", description, values=tuple(values), covariance=covariance)


def _quantities(points: Sequence[Mapping[str, Any]]) -> list[tuple[str, str]]:
    """(quantity, unit) pairs that every validation point gives as reference_<q>_<unit> and measured_<q>_<unit>."""
    first = points[0]
    out = []
    for key in first:
        if key.startswith("reference_"):
            rest = key.removeprefix("reference_")
            q, _, unit = rest.rpartition("_")
            if q and f"measured_{rest}" in first:
                out.append((q, unit))
    return out


def validation_result(validation: Mapping[str, Any], probability: float = COVERAGE, k_bound: float | None = None,
                      budget: Mapping[str, Any] | None = None) -> dcc.Result | None:
    """The validation table (reference, measured, error, each with its expanded uncertainty) and its summary.

    Reads `validation["points"]`: one row per validation point with `reference_<q>_<unit>`,
    `measured_<q>_<unit>`, optionally `u_<q>_<unit>` (expanded uncertainty of the measured value from
    the fit) and `k_<q>` or `k` (its coverage factor). The error is measured − reference. With a
    budget, each point's U combines the fit's part with the budget's (standards, resolution, temperature).
    """
    summary = []
    for key, name in (("rms_deg", "RMS of the errors"), ("max_deg", "largest |error|")):
        if isinstance(validation.get(key), int | float):
            summary.append(dcc.Value(key, name, float(validation[key]), "deg", ref_type="tiltlab_summary"))
    points = validation.get("points") or []
    if isinstance(validation.get("coverage_probability"), int | float):
        probability = float(validation["coverage_probability"])
    if isinstance(validation.get("n_points"), int):
        summary.append(dcc.Value("n_points", "validation points", float(validation["n_points"]), "1",
                                 ref_type="tiltlab_summary"))
    others = reading_components(budget)
    columns: list[dcc.Column] = []
    if points:
        quantities = _quantities(points)
        if not quantities:
            raise CertificateRefused("validation points name no reference_<quantity>_<unit>/measured_... pair")
        for q, unit in quantities:
            ref = tuple(float(p[f"reference_{q}_{unit}"]) for p in points)
            meas = tuple(float(p[f"measured_{q}_{unit}"]) for p in points)
            err = tuple(m - r for m, r in zip(meas, ref, strict=True))
            ukey = f"u_{q}_{unit}"
            has_u = all(isinstance(p.get(ukey), int | float) for p in points)
            U: tuple[float, ...] | None = tuple(float(p[ukey]) for p in points) if has_u else None
            stated = [p.get(f"k_{q}", p.get("k", validation.get("k"))) for p in points]
            if has_u and any(k is None for k in stated) and k_bound is None:
                raise CertificateRefused(f"validation points give {ukey} without its coverage factor")
            # a missing k falls back to the bound, which the refusal above guarantees is there
            ks = tuple(float(k) if k is not None else float(cast(float, k_bound)) for k in stated) if has_u else None
            if U is not None and ks is not None and others and unit == "deg":
                k_arr = np.asarray(ks)
                c = combine(np.asarray(U) / k_arr, dof_of_coverage_factor(k_arr, probability), others, probability)
                U, ks = tuple(float(x) for x in c.U), tuple(float(x) for x in c.k)
            dist = "student-t" if has_u else None
            columns += [
                dcc.Column(f"reference_{q}_{unit}", f"reference {q}", ref, unit, ref_type="basic_referenceValue"),
                dcc.Column(f"measured_{q}_{unit}", f"measured {q} (corrected)", meas, unit, U, ks,
                           probability if has_u else None, ref_type="basic_measuredValue", distribution=dist),
                dcc.Column(f"error_{q}_{unit}", f"error {q} (measured − reference)", err, unit, U, ks,
                           probability if has_u else None, ref_type="basic_measurementError", distribution=dist),
            ]  # fmt: skip
    if not summary and not columns:
        return None
    return dcc.Result(
        "Validation on points not used in the fit",
        "Each validation point was measured after the fit and corrected with the fitted parameters; the error "
        "is the corrected reading minus the reference. The uncertainty of the error is that of the corrected "
        "reading: GUM propagation of the parameters' covariance and the reading noise"
        + (", combined with the uncertainty budget's other components (reference standards, resolution, "
           "temperature)" if others else "")
        + "; k is Student's t at each point's effective degrees of freedom (Welch-Satterthwaite)"
        + ("; where a point does not state its own coverage factor, the one shown is Student's t at the fit's "
           "degrees of freedom, an upper bound of it, and U covers the stated probability." if k_bound else "."),
        values=tuple(summary), columns=tuple(columns), table_ref_type="tiltlab_validationPoint",
    )


def calibration_points_result(points: Sequence[Mapping[str, Any]],
                              stated_range: Mapping[str, Any] | None = None) -> dcc.Result | None:
    """The calibrated range (stated by the record, else the points' extremes of each reference quantity) and the
    calibration points themselves: one column per `<quantity>_<unit>` key of the points."""
    if not points:
        return None
    keys = [k for k in points[0] if "_" in k and all(isinstance(p.get(k), int | float) for p in points)]
    columns = []
    for key in keys:
        q, _, unit = key.rpartition("_")
        columns.append(dcc.Column(key, q.replace("_", " "), tuple(float(p[key]) for p in points), unit,
                                  ref_type="tiltlab_calibrationPoint"))
    ranges: dict[str, tuple[float, float]] = {}
    if stated_range:
        for key, span in stated_range.items():
            if isinstance(span, list | tuple) and len(span) == 2 and "_" in key:
                ranges[f"reference_{key}"] = (float(span[0]), float(span[1]))
    if not ranges:
        for c in columns:
            if c.label.startswith("reference_"):
                ranges[c.label] = (min(c.values), max(c.values))
    values = []
    for label, (lo, hi) in ranges.items():
        q, _, unit = label.rpartition("_")
        name = q.replace("_", " ")
        values += [dcc.Value(f"{label}_min", f"lowest {name}", lo, unit, ref_type="tiltlab_calibratedRange"),
                   dcc.Value(f"{label}_max", f"highest {name}", hi, unit, ref_type="tiltlab_calibratedRange")]
    return dcc.Result(
        "Calibrated range and calibration points",
        f"The {len(points)} points the model was fitted on: the reference's value and the item's indication at "
        "each. The results hold within the range of the reference values.",
        values=tuple(values), columns=tuple(columns), table_ref_type="tiltlab_calibrationPoint",
    )


def _two_digits(u: float) -> float:
    return float(f"{u:.2g}")


def budget_result(budget: Mapping[str, Any] | None) -> dcc.Result | None:
    """The uncertainty budget (GUM): for each result, each contribution's standard uncertainty and the combination."""
    entries = (budget or {}).get("results") or []
    if not entries:
        return None
    values: list[dcc.Value] = []
    for r in entries:
        unit, q = str(r["unit"]), str(r["quantity"])
        for c in r["contributions"]:
            what = "the fit (parameters' covariance and reading noise)" if c["source"] == "fit" else str(c["name"])
            values.append(dcc.Value(f"u_{q}_{c['source']}", f"{r['name']}: u from {what}", _two_digits(c["u"]), unit,
                                    note=_dof_text(c.get("dof")), ref_type="tiltlab_summary"))
        values.append(dcc.Value(f"U_{q}", f"{r['name']}: combined, expanded", float(r["U"]), unit,
                                float(r["U"]), float(r["k"]), float(r["coverage_probability"]),
                                f"u_c = {_two_digits(r['u']):g} {unit}, {_dof_text(r.get('dof_eff'))}",
                                distribution(r.get("dof_eff") or math.inf), ref_type="tiltlab_summary"))
    return dcc.Result(
        "Uncertainty budget",
        "Each result's standard uncertainty components (GUM): the fit, each reference standard (u = U/k of its "
        "certificate; the result is on the reference's angle scale), the sensors' resolution (r/√12) and, where the "
        "temperature varied, its influence; combined by root sum of squares, k from Student's t at the "
        "Welch-Satterthwaite effective degrees of freedom.",
        values=tuple(values),
    )


def temperature_condition(record: Mapping[str, Any], budget: Mapping[str, Any] | None) -> dcc.Condition | None:
    """The measurement sensor's internal temperature: its mean, with the range it lay in as a rectangular U."""
    t = (budget or {}).get("temperature") or {}
    mean = record.get("temp_c") if isinstance(record.get("temp_c"), int | float) else t.get("mean_c")
    if not isinstance(mean, int | float):
        return None
    lo, hi = t.get("min_c", mean), t.get("max_c", mean)
    half = max(float(hi) - mean, mean - float(lo), 0.005)  # at least half the reported 0.01 °C digit
    values = [dcc.Value("temperature_mean", "mean", float(mean), "degC", half, math.sqrt(3.0), 1.0,
                        "the range the readings lay in (rectangular, its half-width as U)", "rectangular",
                        ref_type="tiltlab_internalTemperature")]
    if "min_c" in t:
        values += [dcc.Value("temperature_min", "lowest", float(lo), "degC", ref_type="tiltlab_internalTemperature"),
                   dcc.Value("temperature_max", "highest", float(hi), "degC", ref_type="tiltlab_internalTemperature")]
    return dcc.Condition(
        "temperature", "internal temperature of the measurement sensor",
        tuple(values),
        "The instrument's own internal temperature as it reported it at the calibration points, not a calibrated "
        "thermometer's reading of the ambient air; its own error is not known and not included.",
    )
