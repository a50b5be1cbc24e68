"""The one registry of calibration methods, used by the CLI, the service and the tests.

A method knows which columns it fits on, how to fit, and how to apply a fitted model
(`correct`, and `level` for stage methods). Everything here is pure computation on numpy
arrays keyed by dataset column names.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from service.calibration.model import CalibrationModel
from service.errors import InputError

Columns = Mapping[str, NDArray[np.float64]]


@dataclass
class FitOptions:
    rotation_deg: float = 180.0  # turntable: assumed φ between the two positions of a pair
    loss: str = "linear"  # kinematic: robust loss of least_squares
    extra: dict[str, Any] = field(default_factory=dict)


class Method(Protocol):
    kind: str
    name: str

    @property
    def fit_required(self) -> tuple[str | tuple[str, ...], ...]: ...  # column names or tuples of alternatives

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


_METHODS: dict[tuple[str, str], Method] = {}
_FACTORIES: list[tuple[str, re.Pattern[str], Callable[[re.Match[str]], Method]]] = []


def register(method: Method) -> Method:
    _METHODS[(method.kind, method.name)] = method
    return method


def register_pattern(kind: str, pattern: str, factory: Callable[[re.Match[str]], Method]) -> None:
    """Families of methods such as poly1, poly2, ... built on demand."""
    _FACTORIES.append((kind, re.compile(pattern), factory))


def _load_all() -> None:
    # Importing the method modules registers them; each lives beside this file.
    import importlib
    import pkgutil

    import service.calibration as pkg

    for m in pkgutil.iter_modules(pkg.__path__):
        if m.name.startswith("methods_"):
            importlib.import_module(f"service.calibration.{m.name}")


def get_method(kind: str, name: str) -> Method:
    _load_all()
    if (kind, name) in _METHODS:
        return _METHODS[(kind, name)]
    for k, pat, factory in _FACTORIES:
        if k == kind and (m := pat.fullmatch(name)):
            return factory(m)
    known = sorted(n for (k, n) in _METHODS if k == kind) + [p.pattern for k, p, _ in _FACTORIES if k == kind]
    raise InputError(f"unknown method {name!r} for kind {kind!r}; known: {', '.join(known) or 'none yet'}")


def methods_for(kind: str) -> list[str]:
    _load_all()
    return sorted(n for (k, n) in _METHODS if k == kind)
