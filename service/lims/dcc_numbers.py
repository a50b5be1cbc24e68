"""How a certificate writes units and numbers: D-SI unit strings, and values rounded as GUM 7.2.6
recommends (the expanded uncertainty to two significant digits, the value to the same decimal
place)."""

from __future__ import annotations

import math

from service.lims.dcc_schema import InvalidCertificate

# The lab's unit words (MODEL.json, field-name suffixes) to D-SI unit strings.
_DSI_UNIT = {
    "deg": r"\degree",
    "degree": r"\degree",
    "arcsec": r"\arcsecond",
    "arcmin": r"\arcminute",
    "rad": r"\radian",
    "1": r"\one",
    "count": r"\one",
    "counts": r"\one",
    "reading": r"\one",
    "degC": r"\degreecelsius",
    "C": r"\degreecelsius",
    "K": r"\kelvin",
    "s": r"\second",
    "m": r"\metre",
    "mm": r"\milli\metre",
    "hPa": r"\hecto\pascal",
    "Pa": r"\pascal",
    "%": r"\percent",
}
# digits of a number that has no uncertainty of its own (a reference reading, a covariance)
SIGNIFICANT = 6


def _term_power(unit: str, term: str, sign: int) -> tuple[str, int]:
    """One factor of a unit ('count^2') as its D-SI unit and signed exponent; refused when the word
    has no D-SI equivalent or the power is not an integer."""
    word, _, power = term.strip().partition("^")
    if word not in _DSI_UNIT:
        raise InvalidCertificate(f"unit {unit!r}: {word!r} has no D-SI equivalent")
    try:
        exponent = sign * (int(power) if power else 1)
    except ValueError:
        raise InvalidCertificate(f"unit {unit!r}: exponent {power!r} is not an integer") from None
    return _DSI_UNIT[word], exponent


def unit_powers(unit: str) -> dict[str, int]:
    """{D-SI unit: exponent} of 'deg', 'arcsec/count^2', '1/deg' and the like (pure numbers
    dropped)."""
    text = unit.strip()
    if not text:
        raise InvalidCertificate("a quantity has an empty unit")
    num, _, den = text.partition("/")
    out: dict[str, int] = {}
    for side, sign in ((num, 1), (den, -1)):
        if not side:
            continue
        for term in side.split("*"):
            dsi, exponent = _term_power(unit, term, sign)
            if dsi != r"\one":
                out[dsi] = out.get(dsi, 0) + exponent
    return {dsi: exponent for dsi, exponent in out.items() if exponent}


def render_powers(powers: dict[str, int]) -> str:
    if not powers:
        return r"\one"
    return "".join(
        dsi + (rf"\tothe{{{exponent}}}" if exponent != 1 else "")
        for dsi, exponent in powers.items()
    )


def dsi_unit(unit: str) -> str:
    """D-SI unit string of a lab unit word; a count or a raw reading is a pure number (\\one); an
    unknown word is refused so that no certificate carries a unit nobody can read."""
    return render_powers(unit_powers(unit))


def dsi_product(a: str, b: str) -> str:
    """The D-SI unit of the product of two quantities (a covariance's unit)."""
    powers = dict(unit_powers(a))
    for dsi, exponent in unit_powers(b).items():
        powers[dsi] = powers.get(dsi, 0) + exponent
    return render_powers({dsi: exponent for dsi, exponent in powers.items() if exponent})


def _finite(value: float, what: str) -> float:
    number = float(value)
    if not math.isfinite(number):
        raise InvalidCertificate(f"{what}: {value!r} is not a finite number")
    return number


def _fixed(x: float, decimals: int) -> str:
    text = f"{x:.{decimals}f}" if decimals > 0 else f"{round(x, decimals):.0f}"
    return text.lstrip("-") if float(text) == 0 else text  # no "-0.00"


def gum_decimals(u: float) -> int:
    """Decimal places that give u two significant digits after rounding (0.00996 -> 3: '0.010')."""
    decimals = 1 - math.floor(math.log10(u))
    # rounding carried into a third digit
    if abs(round(u, decimals)) >= 10 ** (2 - decimals) - 10 ** -(decimals + 9):
        decimals -= 1
    return decimals


def gum_pair(value: float, u: float, what: str) -> tuple[str, str, int]:
    """(value, U, decimals) as GUM 7.2.6 gives them: U to two significant digits, the value to the
    same place."""
    number, uncertainty = _finite(value, what), _finite(u, what)
    if uncertainty <= 0:
        return plain(number, what), "0", 0
    decimals = gum_decimals(uncertainty)
    return _fixed(number, decimals), _fixed(uncertainty, decimals), decimals


def at_decimals(value: float, decimals: int, what: str) -> str:
    return _fixed(_finite(value, what), decimals)


def plain(value: float, what: str, significant: int = SIGNIFICANT) -> str:
    """A number without an uncertainty of its own, to `significant` digits (no float artefacts)."""
    number = _finite(value, what)
    if number == 0:
        return "0"
    text = f"{number:.{significant}g}"
    if "e" in text:
        mant, _, exp = text.partition("e")
        return f"{mant}e{int(exp)}"
    return text


def factor(k: float, what: str) -> str:
    """A coverage factor to three significant digits (2.02 for Student's t at 42 degrees of
    freedom)."""
    return plain(k, what, 3)
