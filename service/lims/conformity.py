"""Statements of conformity (ISO/IEC 17025 7.8.6) by the decision rules of ILAC-G8:09/2019.

Pure: a measured error e with its expanded uncertainty U at each point, a largest permissible
error (MPE) and a decision rule give one statement for the quantity:

* simple acceptance: pass if |e| <= MPE at every point, fail otherwise;
* guarded acceptance (w = r·U): pass if |e| <= MPE - w at every point, fail otherwise;
* non-binary: pass if |e| + U <= MPE at every point; fail if some |e| - U > MPE; otherwise, at the
  worst point, conditionalPass if |e| <= MPE < |e| + U, conditionalFail if |e| - U <= MPE < |e|.

The quantity's statement is that of its worst point. Beside it goes the largest probability of
false acceptance over the points (the probability that the true error lies beyond the MPE while
the point passes), from the error's Student's t at its degrees of freedom.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import TypedDict

from scipy import special

from service.calibration.uncertainty import dof_of_coverage_factor
from service.lims.as_found import AXES, AxisAsFound
from service.storage.specification import DecisionRule, Specification

ILAC_G8 = "ILAC-G8:09/2019"


class Conformity(StrEnum):
    """The DCC's words for a statement of conformity, worst last."""

    PASS = "pass"
    CONDITIONAL_PASS = "conditionalPass"
    CONDITIONAL_FAIL = "conditionalFail"
    FAIL = "fail"


_SEVERITY = {conformity: i for i, conformity in enumerate(Conformity)}
IN_WORDS = {
    Conformity.PASS: "conforms (pass)",
    Conformity.CONDITIONAL_PASS: "conforms, but the expanded uncertainty reaches beyond the limit "
    "(conditional pass)",
    Conformity.CONDITIONAL_FAIL: "does not conform, but the limit lies within the expanded "
    "uncertainty (conditional fail)",
    Conformity.FAIL: "does not conform (fail)",
}
RULE_IN_WORDS = {
    DecisionRule.SIMPLE_ACCEPTANCE: "simple acceptance (ILAC-G8 4.2.1, shared risk, no guard "
    "band): a point passes when |e| <= MPE",
    DecisionRule.GUARDED_ACCEPTANCE: "guarded acceptance (ILAC-G8 4.2.2): a point passes when "
    "|e| <= MPE - w, with the guard band w = {fraction:g}·U",
    DecisionRule.NON_BINARY: "non-binary statement (ILAC-G8 4.2.3): pass when |e| + U <= MPE, "
    "conditional pass when |e| <= MPE < |e| + U, conditional fail when |e| - U <= MPE < |e|, "
    "fail when |e| - U > MPE",
}


@dataclass(frozen=True)
class PointError:
    """A measured error with its expanded uncertainty U = k·u (k at `dof` degrees of freedom)."""

    error: float
    expanded_u: float
    k: float
    dof: float = math.inf


@dataclass(frozen=True)
class Decision:
    """The statement of one quantity over its points."""

    conformity: Conformity
    rule: DecisionRule
    max_permissible_error: float
    guard_band_fraction: float
    # the point whose statement is the quantity's (the largest |e| + U among equals)
    worst_index: int
    worst_error: float
    worst_expanded_u: float
    worst_k: float
    worst_dof: float
    largest_false_acceptance: float | None  # over the points that passed; None when none passed
    n_points: int

    def rule_text(self) -> str:
        return RULE_IN_WORDS[self.rule].format(fraction=self.guard_band_fraction)


def point_conformity(
    p: PointError, mpe: float, rule: DecisionRule, guard_band_fraction: float = 1.0
) -> Conformity:
    """One point's statement by the rule (the table in this module's docstring)."""
    abs_error, expanded_u = abs(p.error), p.expanded_u
    if rule is DecisionRule.SIMPLE_ACCEPTANCE:
        return Conformity.PASS if abs_error <= mpe else Conformity.FAIL
    if rule is DecisionRule.GUARDED_ACCEPTANCE:
        guard_band = guard_band_fraction * expanded_u
        return Conformity.PASS if abs_error <= mpe - guard_band else Conformity.FAIL
    if abs_error + expanded_u <= mpe:
        return Conformity.PASS
    if abs_error <= mpe:
        return Conformity.CONDITIONAL_PASS
    if abs_error - expanded_u <= mpe:
        return Conformity.CONDITIONAL_FAIL
    return Conformity.FAIL


def false_acceptance_probability(p: PointError, mpe: float) -> float:
    """The probability that the true error lies outside ±MPE, given the measured e and u = U/k with
    Student's t at the error's degrees of freedom (normal when infinite): what accepting this point
    risks."""
    standard_u = p.expanded_u / p.k if p.k > 0 else 0.0
    if standard_u <= 0:
        return 0.0 if abs(p.error) <= mpe else 1.0
    nu = p.dof if math.isfinite(p.dof) and p.dof > 0 else math.inf

    def cdf(t: float) -> float:
        return float(special.ndtr(t)) if math.isinf(nu) else float(special.stdtr(nu, t))

    return cdf((-mpe - p.error) / standard_u) + 1.0 - cdf((mpe - p.error) / standard_u)


def decide(
    points: Sequence[PointError], mpe: float, rule: DecisionRule, guard_band_fraction: float = 1.0
) -> Decision:
    """The quantity's statement: that of its worst point; with the largest probability of false
    acceptance."""
    if not points:
        raise ValueError("a statement of conformity needs at least one measured point")
    if not (mpe > 0 and math.isfinite(mpe)):
        raise ValueError(f"the largest permissible error {mpe!r} is not a number > 0")
    verdicts = [point_conformity(point, mpe, rule, guard_band_fraction) for point in points]
    worst = max(
        range(len(points)),
        key=lambda i: (_SEVERITY[verdicts[i]], abs(points[i].error) + points[i].expanded_u),
    )
    passed = [
        false_acceptance_probability(point, mpe)
        for point, verdict in zip(points, verdicts, strict=True)
        if verdict in (Conformity.PASS, Conformity.CONDITIONAL_PASS)
    ]
    worst_point = points[worst]
    return Decision(
        verdicts[worst],
        rule,
        mpe,
        guard_band_fraction,
        worst,
        worst_point.error,
        worst_point.expanded_u,
        worst_point.k,
        worst_point.dof,
        max(passed) if passed else None,
        len(points),
    )


@dataclass(frozen=True)
class QuantityDecision:
    """The statement about one quantity: an axis's indication error, or a named parameter (None: not
    assessable)."""

    quantity: str  # "x", "y" or a parameter's name
    name: str  # in words
    unit: str
    decision: Decision | None
    reason: str = ""  # why there is no decision


@dataclass(frozen=True)
class ParameterFigure:
    """A parameter's value with its expanded uncertainty (as the certificate states it)."""

    value: float
    expanded_u: float | None
    k: float | None
    unit: str


class AxisVerdicts(TypedDict, total=False):
    """The statement's word per axis's indication error (None: not assessable)."""

    x: str | None
    y: str | None


class WorstPoint(TypedDict):
    """The error and its expanded uncertainty at the point a quantity's statement rests on."""

    error: float
    expanded_uncertainty: float
    unit: str


class ConformityJson(AxisVerdicts):
    """The statements of conformity as records, orders, the feed and webhooks show them: the word
    per axis, the specification's rule and limit, the word per named parameter (None when the
    specification names none), and per decided quantity the largest probability of false
    acceptance and the worst point."""

    decision_rule: str
    max_permissible_error_deg: float
    guard_band_fraction: float | None
    parameters: dict[str, str | None] | None
    largest_probability_of_false_acceptance: dict[str, float | None]
    worst_point: dict[str, WorstPoint]


@dataclass(frozen=True)
class ConformityReport:
    specification: Specification
    quantities: tuple[QuantityDecision, ...]

    def as_json(self) -> ConformityJson:
        """As records, orders, the feed and webhooks show it."""
        spec = self.specification
        decided = [
            (quantity.quantity, quantity.decision, quantity.unit)
            for quantity in self.quantities
            if quantity.decision
        ]
        return {
            **_axis_verdicts(self.quantities),
            "decision_rule": spec.decision_rule.value,
            "max_permissible_error_deg": spec.max_permissible_error_deg,
            "guard_band_fraction": spec.guard_band_fraction
            if spec.decision_rule is DecisionRule.GUARDED_ACCEPTANCE
            else None,
            "parameters": _verdicts(self.quantities, on_axes=False) if spec.parameters else None,
            "largest_probability_of_false_acceptance": {
                name: decision.largest_false_acceptance for name, decision, _ in decided
            },
            "worst_point": {
                name: {
                    "error": decision.worst_error,
                    "expanded_uncertainty": decision.worst_expanded_u,
                    "unit": unit,
                }
                for name, decision, unit in decided
            },
        }


def _axis_verdicts(quantities: Sequence[QuantityDecision]) -> AxisVerdicts:
    """The statement's word per axis (None: not assessable), in the order of the quantities."""
    out: AxisVerdicts = {}
    for quantity in quantities:
        word = quantity.decision.conformity.value if quantity.decision else None
        # the axes of AXES
        if quantity.quantity == "x":
            out["x"] = word
        elif quantity.quantity == "y":
            out["y"] = word
    return out


def _verdicts(quantities: Sequence[QuantityDecision], *, on_axes: bool) -> dict[str, str | None]:
    """The statement's word per quantity (None: not assessable), of the axes' indication errors or
    of the named parameters."""
    return {
        quantity.quantity: quantity.decision.conformity.value if quantity.decision else None
        for quantity in quantities
        if (quantity.quantity in AXES) == on_axes
    }


def axis_errors(found: Mapping[str, AxisAsFound]) -> dict[str, list[PointError]]:
    """Each axis's indication errors as points to decide on."""
    return {
        axis: [
            PointError(float(error), float(expanded_u), float(k), float(nu))
            for error, expanded_u, k, nu in zip(
                axis_found.error.value,
                axis_found.error.expanded_u,
                axis_found.error.k,
                axis_found.error.dof,
                strict=True,
            )
        ]
        for axis, axis_found in found.items()
    }


def assess(
    spec: Specification, found: Mapping[str, AxisAsFound], parameters: Mapping[str, ParameterFigure]
) -> ConformityReport:
    """The statements a specification asks for: each axis's indication error as found, then each
    named parameter."""
    out = []
    for axis, points in axis_errors(found).items():
        decision = (
            decide(
                points, spec.max_permissible_error_deg, spec.decision_rule, spec.guard_band_fraction
            )
            if points
            else None
        )
        out.append(
            QuantityDecision(
                axis,
                f"indication error, {axis} axis",
                "deg",
                decision,
                "" if points else "no measured points",
            )
        )
    for limit in spec.parameters:
        figure = parameters.get(limit.name)
        if figure is None:
            out.append(
                QuantityDecision(
                    limit.name,
                    f"parameter {limit.name}",
                    "",
                    None,
                    "not a parameter of the record's model",
                )
            )
            continue
        if figure.expanded_u is None or figure.k is None:
            out.append(
                QuantityDecision(
                    limit.name,
                    f"parameter {limit.name}",
                    figure.unit,
                    None,
                    "the parameter was held fixed, not measured",
                )
            )
            continue
        nu = float(dof_of_coverage_factor(figure.k))
        point = PointError(figure.value - limit.nominal, figure.expanded_u, figure.k, nu)
        out.append(
            QuantityDecision(
                limit.name,
                f"parameter {limit.name} (deviation from {limit.nominal:g} {figure.unit})",
                figure.unit,
                decide(
                    [point],
                    limit.max_permissible_error,
                    spec.decision_rule,
                    spec.guard_band_fraction,
                ),
            )
        )
    return ConformityReport(spec, tuple(out))
