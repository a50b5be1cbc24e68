"""The calibration methods, one module per kind (`stage` a package with one module per method), and
the one list of them the registry looks names up in: a method not listed here does not exist."""

from __future__ import annotations

import re

from service.calibration.methods.rotation import DIRECT, IODSRA, IODSRA_COMBINED
from service.calibration.methods.scale import MAX_DEGREE, PolyMethod
from service.calibration.methods.stage import AXIS_TRANSFORM, COUPLING, HOMOGRAPHY, KINEMATIC
from service.calibration.methods.turntable import REVERSAL
from service.calibration.registry import Method, MethodFamily


def _poly(match: re.Match[str]) -> Method:
    return PolyMethod(int(match.group(1)))


METHODS: tuple[Method, ...] = (
    HOMOGRAPHY,
    COUPLING,
    AXIS_TRANSFORM,
    KINEMATIC,  # stage
    DIRECT,
    IODSRA,
    IODSRA_COMBINED,  # rotation
    REVERSAL,  # turntable
)
FAMILIES: tuple[MethodFamily, ...] = (
    MethodFamily(
        "scale",
        re.compile(r"poly(\d+)"),
        _poly,
        tuple(f"poly{n}" for n in range(1, MAX_DEGREE + 1)),
    ),
)
