"""Sensor output against a reference angle (seed 003): methods `poly1`, `poly2`, … (least squares).

Direction. Seed 003 writes its model as y = a x + b (eq. 5), but the number it calls the
measuring unit (a1 = 0.8756, "the angle change per 5/2^12 V", i.e. arcsec per ADC count) is
the slope of angle on reading. The product needs the same direction: `correct` turns a reading
into `angle_arcsec`. So the model is the polynomial angle = Σ c_j · reading^j fitted by least
squares (parameters c0_arcsec, c1_arcsec_per_count, …), applied directly, no inversion. The
paper's own direction (reading on angle) is fitted too and reported in `fit.reading_on_angle`.

Treating the readings as exact in the angle-on-reading fit attenuates the slope by
σ²_reading / var(reading) (≈ 4e-4 for seed 003's table, whose scatter is about 25 counts),
below its standard error of 0.6 %; the direction is chosen for use.

Each model reports the residuals, standard errors (covariance s²(VᵀV)⁻¹), the residual norm
(what seed 003 calls the residual level: its 67.38 and 66.99 are ‖r‖ in arcsec), and F-tests:
is the highest term needed (degree n against n-1), and would the next degree help (n+1 against n).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TypedDict

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.calibration.model import (
    CalibrationModel,
    DegreeFTest,
    FitInfo,
    FTestResult,
    Parameter,
    ReadingOnAngle,
    residual_summary,
)
from service.calibration.registry import Columns, FitOptions
from service.calibration.uncertainty import coverage_factor, propagate_gum
from service.errors import DegenerateDataError, InputError

MAX_DEGREE = 6  # beyond this the monomial coefficients of 12-bit readings lose float64 precision


def reference_arcsec(data: Columns) -> NDArray[np.float64]:
    if "ref_arcsec" in data:
        return np.asarray(data["ref_arcsec"], dtype=float)
    return np.asarray(data["ref_deg"], dtype=float) * 3600.0


def coefficient_names(degree: int) -> list[str]:
    names = ["c0_arcsec", "c1_arcsec_per_count"]
    names += [f"c{j}_arcsec_per_count{j}" for j in range(2, degree + 1)]
    return names[: degree + 1]


def coefficient_unit(j: int) -> str:
    return {0: "arcsec", 1: "arcsec/count"}.get(j, f"arcsec/count^{j}")


class PolyFit(TypedDict):
    """A polynomial fit: coefficients (ascending), their covariance (None without degrees of
    freedom), residuals, RSS, dof and s (None without degrees of freedom)."""

    coef: NDArray[np.float64]
    cov: NDArray[np.float64] | None
    resid: NDArray[np.float64]
    rss: float
    dof: int
    s: float | None


def polyfit(x: NDArray[np.float64], y: NDArray[np.float64], degree: int) -> PolyFit:
    """Least-squares y = Σ c_j x^j, solved in a centred, scaled variable and returned in powers of
    x.

    Returns coefficients (ascending), their covariance (None without degrees of freedom), the
    residuals, RSS, dof and s.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    centre = 0.5 * (x.max() + x.min())
    half = 0.5 * (x.max() - x.min()) or 1.0
    scaled = (x - centre) / half
    vander = np.vander(scaled, degree + 1, increasing=True)
    ortho, tri = np.linalg.qr(vander)
    if np.min(np.abs(np.diag(tri))) < 1e-12 * np.max(np.abs(np.diag(tri))):
        raise DegenerateDataError(
            f"scale: the readings do not determine a degree-{degree} polynomial"
        )
    coef_scaled = np.linalg.solve(tri, ortho.T @ y)
    resid = y - vander @ coef_scaled
    rss = float(resid @ resid)
    dof = x.size - (degree + 1)
    # to_powers maps coefficients in u to those in x: u^k = Σ_j C(k,j) x^j (-centre)^(k-j) / half^k
    to_powers = np.zeros((degree + 1, degree + 1))
    for k in range(degree + 1):
        for j in range(k + 1):
            to_powers[j, k] = math.comb(k, j) * (-centre) ** (k - j) / half**k
    coef = to_powers @ coef_scaled
    cov = None
    sigma = None
    if dof > 0:
        sigma = math.sqrt(rss / dof)
        rinv = np.linalg.inv(tri)
        cov_u = sigma**2 * (rinv @ rinv.T)
        cov = to_powers @ cov_u @ to_powers.T
        cov = 0.5 * (cov + cov.T)
    return {"coef": coef, "cov": cov, "resid": resid, "rss": rss, "dof": dof, "s": sigma}


def f_test(rss_small: float, rss_big: float, dof_big: int) -> FTestResult | None:
    """F-test of one added term: F = (RSS_lower - RSS_higher) / (RSS_higher / dof_higher), F(1,
    dof)."""
    if dof_big <= 0:
        return None
    if rss_big <= 0:
        return {"F": None, "dof": [1, dof_big], "p_value": 0.0, "significant_at_5pct": True}
    # F-distribution upper tail; imported here to keep the CLI start light
    from scipy.special import fdtrc

    f_stat = max(rss_small - rss_big, 0.0) / (rss_big / dof_big)
    p_value = float(fdtrc(1, dof_big, f_stat))
    return {
        "F": f_stat,
        "dof": [1, dof_big],
        "p_value": p_value,
        "significant_at_5pct": bool(p_value < 0.05),
    }


def _monotonic(coef: NDArray[np.float64], lo: float, hi: float) -> bool:
    xs = np.linspace(lo, hi, 2001)
    slope = np.polyval(np.polyder(coef[::-1]), xs)
    return bool(np.all(slope > 0) or np.all(slope < 0))


class PolyMethod:
    kind = "scale"
    fit_required = (("ref_arcsec", "ref_deg"), "reading")
    fit_optional = ()
    correct_required = ("reading",)
    correct_optional = ()
    outputs = ("angle_arcsec", "u_angle_arcsec")

    def __init__(self, degree: int):
        if degree < 1:
            raise InputError(f"scale: poly{degree}: the degree must be at least 1")
        if degree > MAX_DEGREE:
            raise InputError(f"scale: poly{degree}: degrees above {MAX_DEGREE} are not supported")
        self.degree = degree
        self.name = f"poly{degree}"

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel:
        n = self.degree
        ref = reference_arcsec(data)
        reading = np.asarray(data["reading"], dtype=float)
        ref_col = "ref_arcsec" if "ref_arcsec" in data else "ref_deg"
        n_distinct = _distinct_points(n, reading, ref)
        main = polyfit(reading, ref, n)
        names = coefficient_names(n)
        notes: list[str] = []
        params = {
            name: Parameter(float(coef), coefficient_unit(j))
            for j, (name, coef) in enumerate(zip(names, main["coef"]))
        }
        lo, hi = float(reading.min()), float(reading.max())
        slope_mid = float(np.polyval(np.polyder(main["coef"][::-1]), 0.5 * (lo + hi)))
        se = np.sqrt(np.diag(main["cov"])) if main["cov"] is not None else None
        fit: FitInfo = {
            "n_points": int(reading.size),
            "dof": main["dof"],
            "reference_column": ref_col,
            "direction": "angle on reading (applied as is by correct)",
            "residual_sigma_arcsec": main["s"],
            "residual_norm_arcsec": math.sqrt(main["rss"]),
            "standard_errors": {nm: float(std_error) for nm, std_error in zip(names, se)}
            if se is not None
            else None,
            "measuring_unit_arcsec_per_count": float(main["coef"][1]) if n == 1 else slope_mid,
            "reading_range": [lo, hi],
        }
        if n > 1:
            fit["measuring_unit_note"] = (
                "slope d(angle)/d(reading) at the middle of the reading range"
            )
        fit.update(_f_tests(reading, ref, n, main, n_distinct))
        fit["reading_on_angle"] = _reading_on_angle(reading, ref, n)
        monotonic = _monotonic(main["coef"], lo, hi)
        fit["monotonic_over_range"] = monotonic
        if not monotonic:
            notes.append(
                f"poly{n}: the fitted angle is not monotonic in the reading over {lo:g}..{hi:g} "
                "counts: the degree is too high for these data"
            )
        reading_sigma, noise_note = _reading_noise(main["s"], slope_mid)
        notes.append(noise_note)
        notes.append(
            f"angle_arcsec has the zero of the calibration's reference ({ref_col}); readings "
            f"outside {lo:g}..{hi:g} are extrapolated"
        )
        return CalibrationModel(
            kind="scale",
            method=self.name,
            columns=[ref_col, "reading"],
            parameters=params,
            covariance_names=names if main["cov"] is not None else [],
            covariance=main["cov"],
            residuals=residual_summary({"angle_arcsec": main["resid"]}, "arcsec"),
            fit=fit,
            notes=notes,
            state={"degree": n, "reading_sigma_counts": reading_sigma, "dof": main["dof"]},
        )

    def angle(self, model: CalibrationModel, reading: ArrayLike) -> NDArray[np.float64]:
        coef = model.values(coefficient_names(self.degree))
        angle: NDArray[np.float64] = np.polyval(coef[::-1], np.asarray(reading, dtype=float))
        return angle

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, NDArray[np.float64]]:
        names = coefficient_names(self.degree)
        missing = [nm for nm in names if nm not in model.parameters]
        if missing:
            raise InputError(f"scale model {model.method}: parameter {missing[0]!r} missing")
        reading = np.asarray(data["reading"], dtype=float)
        p0 = model.values(names)
        out = {"angle_arcsec": np.polyval(p0[::-1], reading)}
        sigma = (
            model.state.get("reading_sigma_counts") if isinstance(model.state, Mapping) else None
        )
        if model.covariance is not None and sigma is not None:
            # the covariance and the reading noise both come from the fit's residual
            dof = _dof(model)
            gum = propagate_gum(
                lambda p, x: np.polyval(np.asarray(p)[::-1], x["reading"]),
                p0,
                model.cov_of(names),
                {"reading": reading},
                {"reading": float(sigma)},
                dof,
                dof,
            )
            out["u_angle_arcsec"] = gum.expanded()
            out["k_angle"] = coverage_factor(gum.dof_eff)
        return out


def _distinct_points(n: int, reading: NDArray[np.float64], ref: NDArray[np.float64]) -> int:
    """The data's distinct points (the fewer of readings and angles), refused below degree + 1."""
    n_read, n_ref = np.unique(reading).size, np.unique(ref).size
    if n >= n_read or n >= n_ref:
        which = "readings" if n_read <= n_ref else "reference angles"
        raise DegenerateDataError(
            f"scale: poly{n} needs at least {n + 1} distinct points, the data have "
            f"{min(n_read, n_ref)} distinct "
            f"{which} ({reading.size} rows); add points at other angles or lower the degree"
        )
    return min(n_read, n_ref)


def _f_tests(
    reading: NDArray[np.float64],
    ref: NDArray[np.float64],
    n: int,
    main: PolyFit,
    n_distinct: int,
) -> FitInfo:
    """The degree's F-tests: is its highest term needed, and would the next degree help."""
    lower = polyfit(reading, ref, n - 1)
    highest: DegreeFTest = {"against_degree": n - 1}
    tests: FitInfo = {
        "f_test_highest_term": _with_test(highest, f_test(lower["rss"], main["rss"], main["dof"]))
    }
    if reading.size - (n + 2) >= 1 and n + 1 < n_distinct and n + 1 <= MAX_DEGREE:
        higher = polyfit(reading, ref, n + 1)
        next_degree: DegreeFTest = {"degree": n + 1}
        tests["f_test_next_degree"] = _with_test(
            next_degree, f_test(main["rss"], higher["rss"], higher["dof"])
        )
    return tests


def _with_test(degrees: DegreeFTest, test: FTestResult | None) -> DegreeFTest:
    """The degrees tested followed by the test's result (nothing more without one)."""
    if test is None:
        return degrees
    return {**degrees, **test}


def _reading_on_angle(
    reading: NDArray[np.float64], ref: NDArray[np.float64], n: int
) -> ReadingOnAngle:
    """The paper's direction, reading = Σ a_j angle^j, reported beside the model (seed 003)."""
    paper = polyfit(ref, reading, n)
    paper_fit: ReadingOnAngle = {
        "coefficients": [float(coef) for coef in paper["coef"]],
        "units": ["count"]
        + [f"count/arcsec^{j}" if j > 1 else "count/arcsec" for j in range(1, n + 1)],
        "standard_errors": (
            np.sqrt(np.diag(paper["cov"])).tolist() if paper["cov"] is not None else None
        ),
        "residual_norm_counts": math.sqrt(paper["rss"]),
        "residual_sigma_counts": paper["s"],
    }
    if n == 1:
        paper_fit["arcsec_per_count"] = 1.0 / float(paper["coef"][1])
    return paper_fit


def _reading_noise(sigma_arcsec: float | None, slope_mid: float) -> tuple[float | None, str]:
    """The reading noise the residual scatter implies (None without one), and the note saying so."""
    if sigma_arcsec is not None and slope_mid != 0:
        reading_sigma = sigma_arcsec / abs(slope_mid)
        return reading_sigma, (
            f"reading noise {reading_sigma:.3g} counts taken from the residual scatter "
            f"({sigma_arcsec:.3g} arcsec, all of it charged to the reading): used for "
            "u_angle_arcsec"
        )
    return None, "no degrees of freedom left: no standard errors and no u_angle_arcsec"


def _dof(model: CalibrationModel) -> float:
    """Degrees of freedom of the fit (infinite when the model does not say)."""
    dof = model.state.get("dof", model.fit.get("dof"))
    return float(dof) if dof else float("inf")
