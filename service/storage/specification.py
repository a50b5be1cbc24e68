"""What an order's item must meet: the largest permissible error of its indication (and of named
parameters) and the decision rule a statement of conformity follows (ILAC-G8). Checked here, kept
with the order."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, NotRequired, TypedDict

from service.errors import InputError


class DecisionRule(StrEnum):
    """ILAC-G8:09/2019 decision rules a specification may name."""

    SIMPLE_ACCEPTANCE = "simple_acceptance"  # |e| <= MPE passes (shared risk, w = 0)
    GUARDED_ACCEPTANCE = "guarded_acceptance"  # |e| <= MPE - w passes, w = r·U
    NON_BINARY = "non_binary"  # pass, conditional pass, conditional fail, fail


MAX_ERROR_DEG = 90.0
GUARD_BAND_MAX = 3.0
_PARAMETER_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_.]{0,99}")


class SpecificationProblem(InputError):
    """A specification that cannot be used; `field` names where (specification.<...>)."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f"{field}: {reason}")
        self.field = field


class ParameterLimitJson(TypedDict):
    """A parameter's limit as an order keeps it (in the parameter's unit)."""

    nominal: float
    max_permissible_error: float


class SpecificationJson(TypedDict):
    """A specification as an order keeps it (`Order.specification`): the guard band only for
    guarded acceptance, the parameters' limits by name only where there are some."""

    max_permissible_error_deg: float
    decision_rule: str
    guard_band_fraction: NotRequired[float]
    parameters: NotRequired[dict[str, ParameterLimitJson]]


@dataclass(frozen=True)
class ParameterLimit:
    """A named parameter of the model must lie within nominal ± max_permissible_error (in the
    parameter's unit)."""

    name: str
    nominal: float
    max_permissible_error: float


@dataclass(frozen=True)
class Specification:
    max_permissible_error_deg: float
    decision_rule: DecisionRule
    guard_band_fraction: float = 1.0  # guarded acceptance: w = guard_band_fraction · U
    parameters: tuple[ParameterLimit, ...] = ()

    def as_json(self) -> SpecificationJson:
        out: SpecificationJson = {
            "max_permissible_error_deg": self.max_permissible_error_deg,
            "decision_rule": self.decision_rule.value,
        }
        if self.decision_rule is DecisionRule.GUARDED_ACCEPTANCE:
            out["guard_band_fraction"] = self.guard_band_fraction
        if self.parameters:
            out["parameters"] = {
                parameter.name: {
                    "nominal": parameter.nominal,
                    "max_permissible_error": parameter.max_permissible_error,
                }
                for parameter in self.parameters
            }
        return out


def _number(field: str, value: object, *, above: float, most: float) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise SpecificationProblem(field, f"{value!r} is not a number")
    if not above < value <= most:
        raise SpecificationProblem(
            field, f"{value!r} must be greater than {above:g} and at most {most:g}"
        )
    return float(value)


def specification_of(value: object) -> Specification | None:
    """A specification from its JSON form (None when not given); SpecificationProblem names the
    field."""
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise SpecificationProblem(
            "specification", "an object {max_permissible_error_deg, decision_rule} is needed"
        )
    known = {"max_permissible_error_deg", "decision_rule", "guard_band_fraction", "parameters"}
    unknown = sorted(set(value) - known)
    if unknown:
        raise SpecificationProblem(
            f"specification.{unknown[0]}",
            f"unknown; a specification has {', '.join(sorted(known))}",
        )
    mpe = _number(
        "specification.max_permissible_error_deg",
        value.get("max_permissible_error_deg"),
        above=0.0,
        most=MAX_ERROR_DEG,
    )
    rule = _decision_rule_of(value.get("decision_rule"))
    guard = _guard_band_of(value, rule)
    params = _parameter_limits_of(value.get("parameters") or {})
    return Specification(mpe, rule, guard, tuple(params))


def _decision_rule_of(rule_text: object) -> DecisionRule:
    """The decision rule a specification names; SpecificationProblem lists the known ones."""
    try:
        return DecisionRule(str(rule_text))
    except ValueError:
        raise SpecificationProblem(
            "specification.decision_rule",
            f"{rule_text!r} is not one of {', '.join(member.value for member in DecisionRule)}",
        ) from None


def _guard_band_of(value: Mapping[Any, Any], rule: DecisionRule) -> float:
    """The guard band fraction, given only with guarded acceptance (1.0 when not given)."""
    if value.get("guard_band_fraction") is None:
        return 1.0
    if rule is not DecisionRule.GUARDED_ACCEPTANCE:
        raise SpecificationProblem(
            "specification.guard_band_fraction",
            f"a guard band belongs to guarded_acceptance, not {rule.value}",
        )
    return _number(
        "specification.guard_band_fraction",
        value["guard_band_fraction"],
        above=0.0,
        most=GUARD_BAND_MAX,
    )


def _parameter_limits_of(given: object) -> list[ParameterLimit]:
    """The limits on named parameters of the model, each checked where it is given."""
    if not isinstance(given, Mapping):
        raise SpecificationProblem(
            "specification.parameters",
            'an object {"<parameter>": {"nominal": ..., "max_permissible_error": ...}} is needed',
        )
    return [_parameter_limit(name, limit) for name, limit in given.items()]


def _parameter_limit(name: object, limit: object) -> ParameterLimit:
    """One parameter's limit {nominal, max_permissible_error}; the problem names the parameter."""
    field = f"specification.parameters.{name}"
    if not isinstance(name, str) or not _PARAMETER_NAME.fullmatch(name):
        raise SpecificationProblem(
            field, "not a parameter name of a model (letters, digits, '_' and '.')"
        )
    if not isinstance(limit, Mapping) or set(limit) - {"nominal", "max_permissible_error"}:
        raise SpecificationProblem(
            field, 'an object {"nominal": ..., "max_permissible_error": ...} is needed'
        )
    nominal = limit.get("nominal", 0.0)
    if (
        isinstance(nominal, bool)
        or not isinstance(nominal, int | float)
        or not math.isfinite(nominal)
    ):
        raise SpecificationProblem(f"{field}.nominal", f"{nominal!r} is not a number")
    mpe_p = _number(
        f"{field}.max_permissible_error",
        limit.get("max_permissible_error"),
        above=0.0,
        most=1e9,
    )
    return ParameterLimit(name, float(nominal), mpe_p)
