"""Inclinometer on a turntable read in symmetric pairs (seed 004): method `reversal`.

Model (docs/models.md §4). With the pair A, A + φ the half-differences cancel the zeros:

    d1 = (n1(A) - n1(A+φ)) / 2 = m1 sin(φ/2) [ ξ sin(A+β+φ/2)   - η cos(A+β+φ/2)   ]
    d2 = (n2(A) - n2(A+φ)) / 2 = m2 sin(φ/2) [ ξ cos(A+β+ε+φ/2) + η sin(A+β+ε+φ/2) ]

For each pair the 2×2 system gives the compensation (ξ̂, η̂) from the readings; calibration
(seed 004 §3.1, eqs. 9-11) compares it with the star-derived reference (ξ, η) and corrects
β, m1, m2, ε by Gauss-Newton steps (B Δx = b) until they are stable. The start values come
from the same equations solved linearly (they are linear in m·cos and m·sin of β + φ/2), or
from `FitOptions.extra["initial"]` to follow the paper's "assign initial values".

φ is not fitted: only β + φ/2 and m·sin(φ/2) enter, so an error Δφ in the assumed rotation
moves β by -Δφ/2 and scales m1, m2 by 1/cos(Δφ/2) with exactly the same residuals (seed 004
§3.2: 1° of φ moves β by 0.5°). The model says so in its notes.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.calibration.differences import central_jacobian
from service.calibration.model import CalibrationModel, FitInfo, Parameter, residual_summary
from service.calibration.registry import Columns, FitOptions
from service.calibration.uncertainty import coverage_factor, propagate_gum
from service.errors import DegenerateDataError, InputError
from service.io.columns import TURNTABLE_READINGS

PARAM_NAMES = ("beta_deg", "m1_per_arcsec", "m2_per_arcsec", "epsilon_deg")
READING_COLUMNS = TURNTABLE_READINGS
MAX_ITERATIONS = 50


def half_differences(data: Columns) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    d1 = (np.asarray(data["n1_a"], dtype=float) - np.asarray(data["n1_b"], dtype=float)) / 2.0
    d2 = (np.asarray(data["n2_a"], dtype=float) - np.asarray(data["n2_b"], dtype=float)) / 2.0
    return d1, d2


def compensation(
    p: ArrayLike,
    azimuth_deg: ArrayLike,
    d1: NDArray[np.float64],
    d2: NDArray[np.float64],
    rotation_deg: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(ξ̂, η̂) in arcsec from the half-differences: the inverse of the 2×2 pair model."""
    beta, m1, m2, eps = (float(phase_2) for phase_2 in np.asarray(p))
    half_sin = np.sin(np.radians(rotation_deg) / 2.0)
    phase_1 = np.radians(np.asarray(azimuth_deg, dtype=float) + beta + rotation_deg / 2.0)
    phase_2 = phase_1 + np.radians(eps)
    k = half_sin * np.cos(np.radians(eps))
    a1, a2 = d1 / m1, d2 / m2
    xi = (np.sin(phase_2) * a1 + np.cos(phase_1) * a2) / k
    eta = (-np.cos(phase_2) * a1 + np.sin(phase_1) * a2) / k
    return xi, eta


def _tilt_in_instrument_frame(
    az: NDArray[np.float64], xi: NDArray[np.float64], eta: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The reference tilt as the turntable sees it (rotated by -A): what separates β from m."""
    az_rad = np.radians(az)
    return np.column_stack(
        [xi * np.sin(az_rad) - eta * np.cos(az_rad), xi * np.cos(az_rad) + eta * np.sin(az_rad)]
    )


def check_design(
    az: NDArray[np.float64], xi: NDArray[np.float64], eta: NDArray[np.float64]
) -> None:
    """Refuse pairs that cannot separate β, m1, m2, ε, saying what is missing."""
    n = az.size
    if n < 3:
        raise DegenerateDataError(
            f"turntable: {n} symmetric pair(s); beta, m1, m2 and epsilon need at least 3 pairs "
            "(2 equations per pair, and some left over to estimate the scatter)"
        )
    tilt = np.hypot(xi, eta)
    n_az = np.unique(np.round(np.mod(az, 180.0), 6)).size
    n_tilt = np.unique(np.round(np.column_stack([xi, eta]), 6), axis=0).shape[0]
    if np.max(tilt) <= 0.0:
        raise DegenerateDataError(
            "turntable: every reference tilt (ref_north_arcsec, ref_east_arcsec) is zero: with "
            "a plumb axis the readings carry no information on the scale factors or the "
            "installation angle; level the instrument off plumb (several reference tilts) "
            "before calibrating"
        )
    frame_tilt = _tilt_in_instrument_frame(az, xi, eta)
    ev = np.linalg.eigvalsh(frame_tilt.T @ frame_tilt)
    if ev[0] <= 1e-8 * ev[1]:
        raise DegenerateDataError(
            f"turntable: the {n} pairs see the axis tilt along a single direction of the "
            f"instrument ({n_az} distinct azimuth(s) modulo 180°, {n_tilt} distinct reference "
            "tilt(s)), so beta cannot be separated from m1 and m2: add pairs at another azimuth "
            "(not 180° from the first) or at another levelling of the instrument with the tilt "
            "in another direction"
        )


def _initial(
    az: NDArray[np.float64],
    d1: NDArray[np.float64],
    d2: NDArray[np.float64],
    xi: NDArray[np.float64],
    eta: NDArray[np.float64],
    rotation_deg: float,
) -> NDArray[np.float64]:
    """β, m1, m2, ε solved linearly from the half-differences (start of the Gauss-Newton steps)."""
    frame_tilt = _tilt_in_instrument_frame(az, xi, eta)  # columns f1, f2
    half_sin = np.sin(np.radians(rotation_deg) / 2.0)
    # m·cos and m·sin of β + φ/2 (divided by sin(φ/2) with its sign: φ may be negative)
    (m1_cos, m1_sin), *_ = np.linalg.lstsq(frame_tilt, d1 / half_sin, rcond=None)
    (m2_cos, m2_sin), *_ = np.linalg.lstsq(
        np.column_stack([frame_tilt[:, 1], -frame_tilt[:, 0]]), d2 / half_sin, rcond=None
    )
    b_half = np.degrees(np.arctan2(m1_sin, m1_cos))
    c_half = np.degrees(np.arctan2(m2_sin, m2_cos))
    beta = b_half - rotation_deg / 2.0
    eps = c_half - b_half
    beta = (beta + 180.0) % 360.0 - 180.0
    eps = (eps + 180.0) % 360.0 - 180.0
    return np.array([beta, np.hypot(m1_cos, m1_sin), np.hypot(m2_cos, m2_sin), eps])


def _residuals(
    p: NDArray[np.float64],
    az: NDArray[np.float64],
    d1: NDArray[np.float64],
    d2: NDArray[np.float64],
    xi: NDArray[np.float64],
    eta: NDArray[np.float64],
    rotation_deg: float,
) -> NDArray[np.float64]:
    xh, eh = compensation(p, az, d1, d2, rotation_deg)
    return np.concatenate([xi - xh, eta - eh])  # reference (star solution) minus model


# beta, eps in deg; the gains relative to themselves
JACOBIAN_TYPICAL = np.array([10.0, 0.0, 0.0, 10.0])


def _jacobian(
    p: NDArray[np.float64],
    az: NDArray[np.float64],
    d1: NDArray[np.float64],
    d2: NDArray[np.float64],
    xi: NDArray[np.float64],
    eta: NDArray[np.float64],
    rotation_deg: float,
) -> NDArray[np.float64]:
    return central_jacobian(
        lambda q: _residuals(q, az, d1, d2, xi, eta, rotation_deg), p, JACOBIAN_TYPICAL
    )


def gauss_newton(
    p0: ArrayLike,
    az: NDArray[np.float64],
    d1: NDArray[np.float64],
    d2: NDArray[np.float64],
    xi: NDArray[np.float64],
    eta: NDArray[np.float64],
    rotation_deg: float,
    max_iterations: int | None = None,
) -> tuple[NDArray[np.float64], int, bool]:
    """Seed 004 eqs. (9)-(11): x ← x + Δx with B Δx = b, until the parameters are stable."""
    max_iterations = MAX_ITERATIONS if max_iterations is None else max_iterations
    params = np.asarray(p0, dtype=float).copy()
    history = []
    for it in range(1, max_iterations + 1):
        residuals = _residuals(params, az, d1, d2, xi, eta, rotation_deg)
        jacobian = _jacobian(params, az, d1, d2, xi, eta, rotation_deg)
        if not (np.all(np.isfinite(residuals)) and np.all(np.isfinite(jacobian))):
            break
        step, *_ = np.linalg.lstsq(jacobian, -residuals, rcond=None)  # B Δx = b
        params = params + step
        params[1], params[2] = abs(params[1]), abs(params[2])
        scale = np.array(
            [1e-7, 1e-9 * max(abs(params[1]), 1e-300), 1e-9 * max(abs(params[2]), 1e-300), 1e-7]
        )
        history.append(float(np.max(np.abs(step) / scale)))
        if np.all(np.abs(step) <= scale):
            return params, it, True
    return params, len(history), False


def zero_scatter(data: Columns) -> tuple[float, int] | None:
    """Noise of one reading from the half-sums (the zero offsets z1, z2, constant over a cycle),
    with its dof.

    var((n_a + n_b)/2) = σ²/2 for white noise; pooled over both axes and, when a `cycle` column
    is present, within cycles (a slow zero drift between cycles does not count as noise).
    """
    s1 = (np.asarray(data["n1_a"], dtype=float) + np.asarray(data["n1_b"], dtype=float)) / 2.0
    s2 = (np.asarray(data["n2_a"], dtype=float) + np.asarray(data["n2_b"], dtype=float)) / 2.0
    groups = np.asarray(data["cycle"]) if "cycle" in data else np.zeros(s1.size)
    ss, dof = 0.0, 0
    for group in np.unique(groups):
        sel = groups == group
        k = int(np.sum(sel))
        if k < 2:
            continue
        for half_sums in (s1[sel], s2[sel]):
            ss += float(np.sum((half_sums - half_sums.mean()) ** 2))
            dof += k - 1
    if dof < 2:
        return None
    return float(np.sqrt(2.0 * ss / dof)), dof


def _check_rotation(phi: float) -> None:
    """Refuse an assumed pair rotation that leaves no tilt in the half-differences (φ near 0°)."""
    if not np.isfinite(phi) or abs(np.sin(np.radians(phi) / 2.0)) < 0.05:
        raise InputError(
            f"turntable: --rotation-deg {phi:g}: the two positions of a pair must be turned "
            "apart (φ near 180°); at φ near 0° or 360° the half-difference carries no tilt"
        )


def _start(
    init: Mapping[str, float] | None,
    az: NDArray[np.float64],
    d1: NDArray[np.float64],
    d2: NDArray[np.float64],
    xi: NDArray[np.float64],
    eta: NDArray[np.float64],
    phi: float,
) -> NDArray[np.float64]:
    """Where the iteration starts (given, or the linear solution); refused at a scale ≤ 0."""
    p0 = (
        np.array([float(init[k]) for k in PARAM_NAMES])
        if init is not None
        else _initial(az, d1, d2, xi, eta, phi)
    )
    if p0[1] <= 0 or p0[2] <= 0:
        raise DegenerateDataError(
            "turntable: the half-differences do not follow the reference tilts (a scale "
            "factor comes out zero): check the pairing of n*_a and n*_b and the reference "
            "columns"
        )
    return p0


def _iterate(
    p0: NDArray[np.float64],
    az: NDArray[np.float64],
    d1: NDArray[np.float64],
    d2: NDArray[np.float64],
    xi: NDArray[np.float64],
    eta: NDArray[np.float64],
    phi: float,
) -> tuple[NDArray[np.float64], int]:
    """The paper's iteration and its iteration count, refused unless it converges; β to ±180°."""
    fitted, iterations, converged = gauss_newton(p0, az, d1, d2, xi, eta, phi)
    if not converged or not np.all(np.isfinite(fitted)):
        raise DegenerateDataError(
            "turntable: the iterated least squares (seed 004 eqs. 9-11) did not converge in "
            f"{iterations} iterations: the pairs do not determine beta, m1, m2, epsilon "
            "(more pairs, azimuths and reference tilts are needed)"
        )
    fitted[0] = (fitted[0] + 180.0) % 360.0 - 180.0
    return fitted, iterations


def _check_separable(jtj: NDArray[np.float64]) -> None:
    """Refuse normal equations that are singular once scaled: the pairs do not separate β, m, ε."""
    scale = np.sqrt(np.diag(jtj))
    if np.any(scale == 0) or np.linalg.cond(jtj / np.outer(scale, scale)) > 1e12:
        raise DegenerateDataError(
            "turntable: the pairs do not separate beta, m1, m2 and epsilon (singular normal "
            "equations): add pairs at other azimuths and reference tilts"
        )


def _reading_noise(
    halfsum: tuple[float, int] | None, bound_residual: float, dof: int
) -> tuple[float, str, float]:
    """One reading's noise: the smaller upper bound (half-sums or residuals), which, and its dof."""
    bound_halfsum = None if halfsum is None else halfsum[0]
    reading_sigma = bound_residual if bound_halfsum is None else min(bound_residual, bound_halfsum)
    from_halfsums = halfsum is not None and halfsum[0] <= bound_residual
    reading_sigma_from = "half-sums" if from_halfsums else "residuals"
    reading_sigma_dof = halfsum[1] if from_halfsums and halfsum is not None else dof
    return reading_sigma, reading_sigma_from, reading_sigma_dof


def _parameters(fitted: NDArray[np.float64], phi: float) -> dict[str, Parameter]:
    """The fitted β, m1, m2, ε as the model's parameters, and φ held at the assumed rotation."""
    units = ("deg", "reading/arcsec", "reading/arcsec", "deg")
    notes_p = (
        "installation angle of the X axis from the instrument's reference direction (CCD)",
        "scale factor of the X axis, reading units per arcsec",
        "scale factor of the Y axis, reading units per arcsec",
        "non-orthogonality of the two axes",
    )
    params = {
        nm: Parameter(float(value), unit, note=nt)
        for nm, value, unit, nt in zip(PARAM_NAMES, fitted, units, notes_p)
    }
    params["rotation_deg"] = Parameter(
        phi,
        "deg",
        fixed=True,
        note="assumed rotation φ between the two positions of a pair; not fitted",
    )
    return params


class ReversalMethod:
    kind = "turntable"
    name = "reversal"
    fit_required = (
        "azimuth_deg",
        "n1_a",
        "n2_a",
        "n1_b",
        "n2_b",
        "ref_north_arcsec",
        "ref_east_arcsec",
    )
    fit_optional = ("cycle",)
    correct_required = ("azimuth_deg", "n1_a", "n2_a", "n1_b", "n2_b")
    correct_optional = ()
    outputs = ("north_arcsec", "east_arcsec", "u_north_arcsec", "u_east_arcsec")

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel:
        phi = float(options.rotation_deg)
        _check_rotation(phi)
        az = np.asarray(data["azimuth_deg"], dtype=float)
        xi = np.asarray(data["ref_north_arcsec"], dtype=float)
        eta = np.asarray(data["ref_east_arcsec"], dtype=float)
        d1, d2 = half_differences(data)
        check_design(az, xi, eta)
        init = (options.extra or {}).get("initial")
        p0 = _start(init, az, d1, d2, xi, eta, phi)
        fitted, iterations = _iterate(p0, az, d1, d2, xi, eta, phi)
        residuals = _residuals(fitted, az, d1, d2, xi, eta, phi)
        jacobian = _jacobian(fitted, az, d1, d2, xi, eta, phi)
        n = az.size
        dof = 2 * n - 4
        jtj = jacobian.T @ jacobian
        _check_separable(jtj)
        s2 = float(residuals @ residuals) / dof
        cov = s2 * np.linalg.inv(jtj)
        cov = 0.5 * (cov + cov.T)
        m_mean = 0.5 * (fitted[1] + fitted[2])
        reading_sigma, reading_sigma_from, reading_sigma_dof = _reading_noise(
            zero_scatter(data), float(np.sqrt(2.0 * s2) * m_mean), dof
        )
        params = _parameters(fitted, phi)
        n_az = int(np.unique(np.round(np.mod(az, 360.0), 6)).size)
        n_tilt = int(np.unique(np.round(np.column_stack([xi, eta]), 6), axis=0).shape[0])
        notes = [
            (
                "beta and the pair rotation phi cannot be told apart from symmetric pairs: only "
                f"beta + phi/2 enters, so phi is held at the assumed {phi:g} deg; if the true "
                f"rotation is {phi:g} + d deg, the true beta is this beta + d/2 and m1, m2 are "
                "smaller by cos(d/2), with identical residuals (seed 004 §3.2)"
            ),
            (
                f"reading noise {reading_sigma:.3g} (reading units, one reading) from the "
                f"{reading_sigma_from}: the scatter of the half-sums (n_a + n_b)/2, which are "
                "the zero offsets, within each cycle, or the fit residuals with all their "
                "scatter charged to the readings, whichever is smaller (both are upper bounds); "
                "used for u_north_arcsec and u_east_arcsec"
            ),
        ]
        ref_var = s2 - (reading_sigma / m_mean) ** 2 / 2.0
        ref_sigma = float(np.sqrt(ref_var)) if ref_var > 0 else 0.0
        fit: FitInfo = {
            "n_pairs": n,
            "dof": dof,
            "iterations": iterations,
            "converged": True,
            "initial": {nm: float(value) for nm, value in zip(PARAM_NAMES, p0)},
            "initial_from": "given"
            if init is not None
            else "linear solution of the half-difference equations",
            "residual_sigma_arcsec": float(np.sqrt(s2)),
            "n_azimuths": n_az,
            "n_reference_tilts": n_tilt,
            "rotation_deg": phi,
            "reading_sigma": reading_sigma,
            "reading_sigma_from": reading_sigma_from,
            "reference_sigma_arcsec": ref_sigma,
        }
        return CalibrationModel(
            kind="turntable",
            method=self.name,
            columns=list(self.fit_required),
            parameters=params,
            covariance_names=list(PARAM_NAMES),
            covariance=cov,
            residuals=residual_summary(
                {"north_arcsec": residuals[:n], "east_arcsec": residuals[n:]}, "arcsec"
            ),
            fit=fit,
            notes=notes,
            options={"rotation_deg": phi},
            state={
                "reading_sigma": reading_sigma,
                "reading_sigma_dof": reading_sigma_dof,
                "dof": dof,
            },
        )

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, NDArray[np.float64]]:
        p0 = model.values(PARAM_NAMES)
        phi = model.value("rotation_deg") if "rotation_deg" in model.parameters else 180.0
        az = np.asarray(data["azimuth_deg"], dtype=float)
        d1, d2 = half_differences(data)
        xi, eta = compensation(p0, az, d1, d2, phi)
        out = {"north_arcsec": xi, "east_arcsec": eta}
        sigma = model.state.get("reading_sigma") if isinstance(model.state, Mapping) else None
        if model.covariance is not None and sigma is not None:
            inputs = {
                reading_column: np.asarray(data[reading_column], dtype=float)
                for reading_column in READING_COLUMNS
            }

            def f(
                p: NDArray[np.float64], x: Mapping[str, NDArray[np.float64]]
            ) -> NDArray[np.float64]:
                h1, h2 = half_differences(x)
                return np.column_stack(compensation(p, az, h1, h2, phi))

            dof = float(model.state.get("dof") or model.fit.get("dof") or np.inf)
            sigma_dof = float(model.state.get("reading_sigma_dof") or np.inf)
            gum = propagate_gum(
                f,
                p0,
                model.cov_of(list(PARAM_NAMES)),
                inputs,
                {reading_column: float(sigma) for reading_column in READING_COLUMNS},
                dof,
                sigma_dof,
            )
            expanded, k = gum.expanded(), np.broadcast_to(coverage_factor(gum.dof_eff), gum.u.shape)
            out["u_north_arcsec"], out["u_east_arcsec"] = expanded[:, 0], expanded[:, 1]
            out["k_north"], out["k_east"] = k[:, 0], k[:, 1]
        return out


REVERSAL = ReversalMethod()
