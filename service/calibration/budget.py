"""The uncertainty budget of a calibration result in the GUM manner (JCGM 100 §5, §8).

A corrected tilt (and a parameter that carries the reference's angle scale, such as a zero
offset) takes its uncertainty from independent components, each a standard uncertainty in
degrees with its degrees of freedom:

* the fit: the parameters' covariance and the reading noise (type A, Student's t at the fit's
  degrees of freedom), as the method propagates it;
* the reference standard the reference sensor's angle scale was transferred from: u = U / k of
  its certificate (type B), with the degrees of freedom its stated k implies at 95 %; the
  corrected tilt is in the reference's frame, so its sensitivity is 1;
* each sensor's resolution (the last digit of its output): rectangular, u = r / √12;
* where the temperature varied during the calibration, its influence: the fit's residuals
  regressed on temperature give a coefficient c (deg/°C) the model does not correct for; over
  the temperature span ΔT that is rectangular with u = |c|·ΔT / √12.

They combine as u_c² = Σ u_i², with the Welch-Satterthwaite effective degrees of freedom and the
coverage factor of Student's t at them (95 %). Pure: the caller supplies every number.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NotRequired, TypedDict, cast

import numpy as np
from numpy.typing import NDArray

from service.calibration.uncertainty import COVERAGE, coverage_factor, dof_of_coverage_factor

SQRT12 = math.sqrt(12.0)
# a span below this is a constant temperature (the sensors' 0.01 °C digits, noise)
TEMPERATURE_VARIED_C = 0.05
ANGLE_UNITS = {"deg": 1.0, "arcsec": 3600.0, "arcmin": 60.0}  # unit per degree


class BudgetComponent(TypedDict):
    """A shared component as a record's budget keeps it (`components`): a standard uncertainty in
    degrees; `dof` null where infinite. Budgets stored before distribution, evaluation and note
    were kept lack them."""

    source: str
    name: str
    u_deg: float
    dof: float | None
    distribution: NotRequired[str]
    evaluation: NotRequired[str]
    note: NotRequired[str]


class BudgetContribution(TypedDict):
    """One row of a result's budget: a component's standard uncertainty in the result's unit (the
    fit's own row has no name)."""

    source: str
    name: NotRequired[str]
    standard_uncertainty: float
    dof: float | None


class BudgetResult(TypedDict):
    """One result's budget (`results`): its contributions and their combination, in `unit`."""

    quantity: str
    name: str
    unit: str
    contributions: list[BudgetContribution]
    standard_uncertainty: float
    dof_eff: float | None
    coverage_factor: float
    expanded_uncertainty: float
    coverage_probability: float


class TemperatureStats(TypedDict, total=False):
    """The calibration points' temperature (°C): empty without temperatures, only `n_points` when
    too few carry one, the coefficient only where the temperature varied."""

    min_c: float
    max_c: float
    mean_c: float
    span_c: float
    n_points: int
    coefficient_deg_per_c: float


class UncertaintyBudget(TypedDict):
    """A record's uncertainty budget (the record's `budget`, results under their present names):
    the shared components, the temperature and one entry per result; `traceable` (and `warning`
    where it is not) once service.jobs.budgets has judged it."""

    coverage_probability: float
    components: list[BudgetComponent]
    temperature: TemperatureStats
    results: list[BudgetResult]
    traceable: NotRequired[bool]
    warning: NotRequired[str]


class ReferenceStandard(TypedDict):
    """A reference standard as the budget reads it: its certificate's expanded uncertainty
    (degrees) and coverage factor, None where the certificate states none."""

    name: str
    serial: str
    certificate_id: NotRequired[str]
    expanded_uncertainty_deg: float | None
    coverage_factor: float | None


@dataclass(frozen=True)
class Component:
    """One independent contribution, already multiplied by its sensitivity: a standard uncertainty
    in degrees."""

    source: str  # fit | reference_standard | resolution | temperature
    name: str
    u_deg: float
    dof: float = math.inf
    distribution: str = "normal"  # normal | rectangular | student-t
    evaluation: str = "B"  # A (statistics of the data) or B (stated: a certificate, a resolution)
    note: str = ""

    def as_json(self) -> BudgetComponent:
        return {
            "source": self.source,
            "name": self.name,
            "u_deg": self.u_deg,
            "dof": None if not math.isfinite(self.dof) else self.dof,
            "distribution": self.distribution,
            "evaluation": self.evaluation,
            "note": self.note,
        }


def component_of_json(d: BudgetComponent) -> Component:
    dof = d.get("dof")
    return Component(
        str(d["source"]),
        str(d["name"]),
        float(d["u_deg"]),
        math.inf if dof is None else float(dof),
        str(d.get("distribution", "normal")),
        str(d.get("evaluation", "B")),
        str(d.get("note", "")),
    )


def standard_component(
    name: str, expanded_deg: float, k: float, coverage: float = COVERAGE
) -> Component:
    """A reference standard's certificate: u = U / k.

    Its degrees of freedom are those for which Student's t gives the stated k at the coverage
    probability (k = 2 at 95 %: about 60; infinite for k at or below the normal's 1.96), so that
    where the standard dominates, the result's U is the standard's own U, not shrunk to 1.96·u.
    """
    nu = float(dof_of_coverage_factor(k, coverage))
    return Component(
        "reference_standard",
        name,
        expanded_deg / k,
        nu,
        "student-t" if math.isfinite(nu) else "normal",
        note=f"U = {expanded_deg:.3g} deg, k = {k:g}: u = U/k"
        + (f", {nu:.0f} degrees of freedom from k at {coverage:.0%}" if math.isfinite(nu) else ""),
    )


def resolution_component(name: str, resolution_deg: float) -> Component:
    """A digital output's last digit: rectangular over ±r/2, u = r/√12."""
    return Component(
        "resolution",
        name,
        resolution_deg / SQRT12,
        distribution="rectangular",
        note=f"resolution {resolution_deg:.3g} deg: u = r/√12",
    )


def temperature_component(
    temps_c: NDArray[np.float64], errors_deg: NDArray[np.float64]
) -> tuple[Component | None, TemperatureStats]:
    """The temperature's influence left in the fit's residuals, and the temperature's statistics.

    Returns (None, stats) where the temperature did not vary (span below TEMPERATURE_VARIED_C) or
    too few points carry one. `errors_deg` is (n,) or (n, axes): the larger axis's coefficient
    counts.
    """
    t = np.asarray(temps_c, dtype=float)
    errors = np.asarray(errors_deg, dtype=float).reshape(t.size, -1)
    ok = np.isfinite(t) & np.all(np.isfinite(errors), axis=1)
    t, errors = t[ok], errors[ok]
    if t.size < 3:
        return None, {"n_points": int(t.size)}
    span = float(t.max() - t.min())
    stats: TemperatureStats = {
        "min_c": float(t.min()),
        "max_c": float(t.max()),
        "mean_c": float(t.mean()),
        "span_c": span,
        "n_points": int(t.size),
    }
    if span < TEMPERATURE_VARIED_C:
        return None, stats
    design = np.column_stack([np.ones_like(t), t - t.mean()])
    slopes = np.linalg.lstsq(design, errors, rcond=None)[0][1]
    coefficient = float(np.max(np.abs(slopes)))
    stats["coefficient_deg_per_c"] = coefficient
    return Component(
        "temperature",
        f"temperature influence over {span:.2f} °C (not corrected by the model)",
        coefficient * span / SQRT12,
        distribution="rectangular",
        note=f"|c| = {coefficient:.3g} deg/°C from the fit's residuals against temperature: "
        "u = |c|·ΔT/√12",
    ), stats


@dataclass(frozen=True)
class Combined:
    u: NDArray[np.float64]
    dof_eff: NDArray[np.float64]
    k: NDArray[np.float64]
    U: NDArray[np.float64]


def combine(
    u_fit: NDArray[np.float64] | float,
    dof_fit: NDArray[np.float64] | float,
    others: Sequence[Component],
    coverage: float = COVERAGE,
) -> Combined:
    """u_c = √(u_fit² + Σ u_i²) with Welch-Satterthwaite degrees of freedom and U = k·u_c
    (vectorised over u_fit)."""
    uf = np.asarray(u_fit, dtype=float)
    nu = np.broadcast_to(np.asarray(dof_fit, dtype=float), uf.shape)
    parts: list[tuple[NDArray[np.float64], float]] = []
    var = uf**2
    total = var.copy()
    for other in others:
        total = total + other.u_deg**2
    # the fit's ν may differ per reading: ν_eff = u_c⁴ / (u_fit⁴/ν_fit + Σ u_i⁴/ν_i)
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = np.where(np.isfinite(nu), var**2 / np.where(np.isfinite(nu), nu, 1.0), 0.0)
    for other in others:
        if math.isfinite(other.dof):
            parts.append((np.full(uf.shape, other.u_deg**2), other.dof))
    if parts:
        denom = denom + sum(part_var**2 / part_dof for part_var, part_dof in parts)
    with np.errstate(divide="ignore", invalid="ignore"):
        dof = np.where(denom > 0, total**2 / np.where(denom > 0, denom, 1.0), np.inf)
    k = np.asarray(coverage_factor(dof, coverage), dtype=float)
    u_c = np.sqrt(total)
    return Combined(u_c, dof, k, k * u_c)


def model_dof(model: Mapping[str, object]) -> float:
    """Degrees of freedom of the fit behind the parameters' covariance: the smallest any part
    states.

    A model may state several (a kinematic chain and the measurement sensor fit separately); the
    smallest gives the largest coverage factor, so the interval is never too narrow. Infinite when
    the model states none (k = 1.96 at 95 %).
    """
    found: list[float] = []

    def walk(node: object) -> None:
        if isinstance(node, Mapping):
            for k, value in node.items():
                if (
                    k in ("dof", "meas_dof")
                    and isinstance(value, int | float)
                    and not isinstance(value, bool)
                    and value > 0
                ):
                    found.append(float(value))
                else:
                    walk(value)

    walk(model.get("fit") or {})
    walk(model.get("state") or {})
    return min(found) if found else math.inf


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def result_entry(
    quantity: str,
    name: str,
    unit: str,
    u_fit_deg: float,
    dof_fit: float,
    others: Sequence[Component],
    coverage: float = COVERAGE,
) -> BudgetResult:
    """One result's budget: its contributions (in the result's unit) and their combination."""
    scale = ANGLE_UNITS.get(unit, 1.0)
    combined = combine(np.array([u_fit_deg]), np.array([dof_fit]), others, coverage)
    rows: list[BudgetContribution] = [
        {"source": "fit", "standard_uncertainty": u_fit_deg * scale, "dof": _finite(dof_fit)}
    ]
    rows += [
        {
            "source": other.source,
            "name": other.name,
            "standard_uncertainty": other.u_deg * scale,
            "dof": _finite(other.dof),
        }
        for other in others
    ]
    return {
        "quantity": quantity,
        "name": name,
        "unit": unit,
        "contributions": rows,
        "standard_uncertainty": float(combined.u[0]) * scale,
        "dof_eff": _finite(float(combined.dof_eff[0])),
        "coverage_factor": float(combined.k[0]),
        "expanded_uncertainty": float(combined.U[0]) * scale,
        "coverage_probability": coverage,
    }


# A result's keys in budgets stored before they were named in words (u, U and k: two differ only by
# case, which some JSON mappers cannot tell apart). Stored records keep their bytes (they are
# hashed); readers get the names.
_FORMER_RESULT_KEYS = {
    "u": "standard_uncertainty",
    "U": "expanded_uncertainty",
    "k": "coverage_factor",
}


def current_names(budget: Mapping[str, object] | None) -> UncertaintyBudget | None:
    """A stored budget with its results' uncertainties under their present names, whenever it was
    stored."""
    if budget is None:
        return None
    results = []
    for result in cast("list[Mapping[str, object]]", budget.get("results") or []):
        entry = {_FORMER_RESULT_KEYS.get(key, key): value for key, value in result.items()}
        contributions = cast("list[Mapping[str, object]]", result.get("contributions") or [])
        entry["contributions"] = [
            {
                ("standard_uncertainty" if key == "u" else key): value
                for key, value in contribution.items()
            }
            for contribution in contributions
        ]
        results.append(entry)
    # the stored keys, renamed: what UncertaintyBudget states
    return cast(UncertaintyBudget, {**budget, "results": results})


def carries_reference_scale(name: str, unit: str) -> bool:
    """A parameter whose value is an angle read on the reference's scale: a zero offset (not a
    scale, a yaw)."""
    return unit in ANGLE_UNITS and ("zero" in name or "offset" in name)


def record_budget(
    *,
    parameters: Mapping[str, Mapping[str, object]],
    parameter_u: Mapping[str, float],
    dof_fit: float,
    standards: Sequence[ReferenceStandard],
    resolutions_deg: Mapping[str, float | None],
    tilt_u_fit_deg: tuple[float, float] | None = None,
    tilt_dof_fit: tuple[float, float] | None = None,
    temps_c: NDArray[np.float64] | None = None,
    errors_deg: NDArray[np.float64] | None = None,
    coverage: float = COVERAGE,
) -> UncertaintyBudget:
    """The budget a record keeps: the shared components and one entry per result.

    `standards`: {"name", "serial", "certificate_id", "expanded_uncertainty_deg", "coverage_factor"}
    each; `parameter_u`: each fitted parameter's standard uncertainty from the covariance (its own
    unit); `resolutions_deg`: each sensor's resolution by what it is ("measurement sensor",
    "reference sensor"); `tilt_u_fit_deg`: the fit's standard uncertainty of a corrected tilt per
    axis (RMS over the calibration points), with its degrees of freedom; `temps_c`/`errors_deg`: the
    calibration points' temperatures and residuals (corrected minus reference) for the temperature's
    influence.
    """
    comps: list[Component] = [_certificate_component(standard) for standard in standards]
    comps += [
        resolution_component(f"{what} resolution", float(resolution))
        for what, resolution in resolutions_deg.items()
        if resolution
    ]
    temperature: TemperatureStats = {}
    if temps_c is not None and errors_deg is not None:
        tc, temperature = temperature_component(temps_c, errors_deg)
        if tc is not None:
            comps.append(tc)
    results: list[BudgetResult] = []
    if tilt_u_fit_deg is not None:
        dofs = tilt_dof_fit or (dof_fit, dof_fit)
        results += _tilt_results(tilt_u_fit_deg, dofs, comps, coverage)
    results += _reference_scale_results(parameters, parameter_u, dof_fit, comps, coverage)
    return {
        "coverage_probability": coverage,
        "components": [comp.as_json() for comp in comps],
        "temperature": temperature,
        "results": results,
    }


def _certificate_component(standard: ReferenceStandard) -> Component:
    """A reference standard as its certificate states it; refused when it states no uncertainty."""
    expanded, k = standard.get("expanded_uncertainty_deg"), standard.get("coverage_factor")
    if expanded is None or k is None:
        raise ValueError(
            f"reference standard {standard.get('name')!r} states no numeric uncertainty"
        )
    return standard_component(
        f"{standard['name']} (serial {standard['serial']}, "
        f"certificate {standard.get('certificate_id')})",
        float(expanded),
        float(k),
    )


def _tilt_results(
    tilt_u_fit_deg: tuple[float, float],
    dofs: tuple[float, float],
    comps: Sequence[Component],
    coverage: float,
) -> list[BudgetResult]:
    """The corrected tilt's result per axis: every shared component adds to it."""
    return [
        result_entry(
            f"tilt_{axis}_deg",
            f"corrected table tilt, {axis} (at the calibration points)",
            "deg",
            u_fit,
            nu,
            comps,
            coverage,
        )
        for axis, u_fit, nu in zip("xy", tilt_u_fit_deg, dofs, strict=True)
    ]


def _reference_scale_results(
    parameters: Mapping[str, Mapping[str, object]],
    parameter_u: Mapping[str, float],
    dof_fit: float,
    comps: Sequence[Component],
    coverage: float,
) -> list[BudgetResult]:
    """A result per parameter read on the reference's angle scale: only the standards add to it."""
    angle_scale = [comp for comp in comps if comp.source == "reference_standard"]
    results: list[BudgetResult] = []
    for name, param in parameters.items():
        unit = str(param.get("unit", ""))
        if name not in parameter_u or not carries_reference_scale(name, unit):
            continue
        results.append(
            result_entry(
                name,
                name,
                unit,
                parameter_u[name] / ANGLE_UNITS[unit],
                dof_fit,
                angle_scale,
                coverage,
            )
        )
    return results


def reading_components(budget: Mapping[str, object] | None) -> list[Component]:
    """What adds to the fit's uncertainty of every corrected reading (the standards, resolutions,
    temperature)."""
    if not budget:
        return []
    components = cast("list[BudgetComponent]", budget.get("components") or [])
    return [component_of_json(component) for component in components]
