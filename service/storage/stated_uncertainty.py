"""A reference standard's uncertainty as a number: read from the free text its certificate states.

"0.001 deg (k = 2)", "U = 3.6 arcsec, k = 2", "±0.5″ (k=2)" give the expanded uncertainty in degrees
and its coverage factor; anything else (another unit, no coverage factor) gives nothing, so that a
standard whose uncertainty cannot be read is refused where it would be used rather than guessed at.
The same rule fills the numbers of standards registered before they were kept as numbers.
"""

from __future__ import annotations

import math
import re

# degrees per unit of the units a certificate states an angle's uncertainty in
ANGLE_UNITS_DEG = {
    "deg": 1.0,
    "degree": 1.0,
    "degrees": 1.0,
    "°": 1.0,
    "arcmin": 1.0 / 60.0,
    "′": 1.0 / 60.0,
    "'": 1.0 / 60.0,
    "arcsec": 1.0 / 3600.0,
    "″": 1.0 / 3600.0,
    '"': 1.0 / 3600.0,
    "arc sec": 1.0 / 3600.0,
    "as": 1.0 / 3600.0,
    "mrad": 180.0 / math.pi / 1e3,
    "µrad": 180.0 / math.pi / 1e6,
    "urad": 180.0 / math.pi / 1e6,
    "rad": 180.0 / math.pi,
}

_UNIT = "|".join(sorted((re.escape(unit) for unit in ANGLE_UNITS_DEG), key=len, reverse=True))
_TEXT = re.compile(
    rf"^\s*(?:U\s*=\s*)?(?:±|\+/-)?\s*(?P<value>\d+(?:\.\d*)?(?:[eE][-+]?\d+)?|\.\d+)\s*(?P<unit>{_UNIT})(?![A-Za-z])"
    r"\s*[,;(]?\s*k\s*=\s*(?P<k>\d+(?:\.\d*)?)\s*\)?\s*$"
)


def parse_stated_uncertainty(text: str | None) -> tuple[float, float] | None:
    """(expanded uncertainty in degrees, coverage factor) from a certificate's wording, or None."""
    if not text:
        return None
    m = _TEXT.match(text)
    if m is None:
        return None
    value, k = float(m["value"]), float(m["k"])
    if not (value > 0 and math.isfinite(value) and k >= 1 and math.isfinite(k)):
        return None
    return value * ANGLE_UNITS_DEG[m["unit"]], k
