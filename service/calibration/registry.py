"""The one registry of calibration methods, used by the CLI, the service and the tests.

The methods themselves are listed in service.calibration.methods; this module says what a method is
and finds one by kind and name.

A method knows which columns it fits on, how to fit, and how to apply a fitted model
(`correct`, and `level` for stage methods). Everything here is pure computation on numpy
arrays keyed by dataset column names.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cache
from typing import Protocol, TypedDict, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from service.calibration.model import CalibrationModel
from service.errors import InputError
from service.physics.stage import StageBench

Columns = Mapping[str, NDArray[np.float64]]


class FitExtras(TypedDict, total=False):
    """A method's own fit options. Turntable: the iteration's start values (`initial`, by
    parameter). Stage: the bench and where it was stated, the measurement sensor's mounting
    (`meas_flip`: auto, none, x, y), the reference's noise (degrees, one reading); homography: the
    H1 points and the off-axis term; kinematic: the effects added, the worm's periodic error, the
    solver's evaluations and the stages whose worm is fitted."""

    initial: Mapping[str, float]
    bench: StageBench
    bench_source: str
    meas_flip: str
    ref_noise_deg: float
    points: str
    offaxis: str
    effects: list[str]
    periodic_error: bool
    max_nfev: int
    worm_axes: list[str]


@dataclass
class FitOptions:
    rotation_deg: float = 180.0  # turntable: assumed φ between the two positions of a pair
    loss: str = "linear"  # kinematic: robust loss of least_squares
    extra: FitExtras = field(default_factory=lambda: FitExtras())


class Method(Protocol):
    kind: str
    name: str

    @property
    # column names or tuples of alternatives
    def fit_required(self) -> tuple[str | tuple[str, ...], ...]: ...

    @property
    def fit_optional(self) -> tuple[str, ...]: ...

    @property
    def correct_required(self) -> tuple[str | tuple[str, ...], ...]: ...

    @property
    def correct_optional(self) -> tuple[str, ...]: ...

    @property
    def outputs(self) -> tuple[str, ...]: ...  # columns `correct` adds

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel: ...

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, NDArray[np.float64]]: ...


@runtime_checkable
class LevellingMethod(Method, Protocol):
    """A stage method: it also levels (wanted table tilt -> stage commands)."""

    def level(self, model: CalibrationModel, data: Columns) -> dict[str, NDArray[np.float64]]: ...


def levelling_method(kind: str, name: str) -> LevellingMethod:
    """The method of a stage model, as one that levels; refused for a method that cannot."""
    method = get_method(kind, name)
    if not isinstance(method, LevellingMethod):
        raise InputError(f"method {kind}/{name} does not level; levelling needs a stage model")
    return method


@dataclass(frozen=True)
class MethodFamily:
    """Methods of one kind built on demand from their name, such as poly1, poly2, ... of `scale`."""

    kind: str
    pattern: re.Pattern[str]
    build: Callable[[re.Match[str]], Method]
    members: tuple[str, ...] = ()  # the names the family takes (what a request may name)


@cache
def _table() -> tuple[dict[tuple[str, str], Method], tuple[MethodFamily, ...]]:
    # Imported on first use, not with this module: the methods import the types above, and a
    # command's --help need not load scipy.
    from service.calibration.methods import FAMILIES, METHODS

    return {(m.kind, m.name): m for m in METHODS}, FAMILIES


def get_method(kind: str, name: str) -> Method:
    methods, families = _table()
    if (kind, name) in methods:
        return methods[(kind, name)]
    for family in families:
        if family.kind == kind and (m := family.pattern.fullmatch(name)):
            return family.build(m)
    known = sorted(n for (k, n) in methods if k == kind) + [
        method_family.pattern.pattern for method_family in families if method_family.kind == kind
    ]
    raise InputError(
        f"unknown method {name!r} for kind {kind!r}; known: {', '.join(known) or 'none yet'}"
    )


def known_methods(kind: str) -> list[str]:
    """Every method name of a kind a request may give: the named methods and each family's
    members."""
    methods, families = _table()
    return sorted(n for (k, n) in methods if k == kind) + [
        n for family in families if family.kind == kind for n in family.members
    ]


def methods_for(kind: str) -> list[str]:
    """The named methods of a kind (families such as poly1, poly2, ... are not listed)."""
    methods, _ = _table()
    return sorted(n for (k, n) in methods if k == kind)
