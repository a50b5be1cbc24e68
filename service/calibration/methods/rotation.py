"""Rotation about an inclined axis (seed 002): methods `direct`, `iodsra` and `iodsra-combined`.

Geometry (docs/models.md §3): the outputs S = (Sx, Sy, Sz) are the vertical expressed in the
sensor frame, so as the body turns about the fixed axis L they run on a circle of the unit
sphere: the plane of eq. (10), unit normal n = (sin α cos γ, cos α cos γ, -sin γ) (L in the
sensor frame) at distance sin β from the origin. α, β, γ come from a least-squares plane
through the points (the orthogonal-distance fit eq. 10 allows; three points give the paper's
exact solution), and θ from the rotation equations (7)-(9).

* `direct`: the baseline of seed 002 §2.1 (its ref. [12]): Sz from eq. (6) with Sz ≥ 0 (any
  measured sz is ignored). Beyond the angle where the true Sz changes sign it is wrong.
* `iodsra`: the measured sz, with the 45° rule of §2.2 (a component whose magnitude exceeds
  sin 45° is replaced by the value from eq. (6), keeping its sign), then θ by the paper's
  choice: eq. (9) near ±90° (45° < |θ| < 135°), eq. (7) elsewhere, each equation's branch or
  sign taken from the other.
* `iodsra-combined`: the same points and fit, θ from all three equations together: the
  least-squares angle on the circle, θ = atan2(S·e2, S·e1), i.e. atan2 of eq. (7) and of
  eq. (9)·cos γ + eq. (8)·sin γ. Never worse than the switch, √2 better at |θ| = 45°, 135°.

The sense of the axis (L or -L) is a convention the points alone cannot fix: β ≥ 0 unless a
`theta_ref_deg` column says otherwise (then the sense that reproduces it is taken).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.calibration.model import (
    CalibrationModel,
    ConstantErrorArc,
    FitInfo,
    Parameter,
    residual_summary,
)
from service.calibration.registry import Columns, FitOptions
from service.calibration.uncertainty import (
    Propagated,
    coverage_factor,
    expanded_with_bias,
    propagate_gum,
    welch_satterthwaite,
)
from service.errors import DegenerateDataError

SIN45 = float(np.sin(np.radians(45.0)))
PARAM_NAMES = ("alpha_deg", "beta_deg", "gamma_deg")
# MODEL.json state: per branch, the line fit of their θ bias
CONSTANT_ERRORS_KEY: Final = "theta_constant_output_errors"


def _local(theta_deg: ArrayLike, centre_deg: float, linear: bool) -> NDArray[np.float64]:
    """Design of a straight line in θ about a branch's centre (radians, wrapped), or of its mean
    alone."""
    offset_rad = np.radians(wrap_deg(np.asarray(theta_deg, dtype=float) - centre_deg))
    return (
        np.column_stack([np.ones_like(offset_rad), offset_rad])
        if linear
        else np.ones((offset_rad.size, 1))
    )


# --- points -------------------------------------------------------------------------------------


def direct_points(sx: ArrayLike, sy: ArrayLike) -> NDArray[np.float64]:
    """(Sx, Sy, Sz) with Sz = +sqrt(1 - Sx² - Sy²) (eq. 6 and the direct method's Sz ≥ 0 rule)."""
    x, y = np.asarray(sx, dtype=float), np.asarray(sy, dtype=float)
    z = np.sqrt(np.clip(1.0 - x**2 - y**2, 0.0, None))
    return np.column_stack([x, y, z])


def iodsra_points(
    sx: ArrayLike, sy: ArrayLike, sz: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Seed 002 §2.2 (2): the one component above sin 45° (if any) replaced by eq. (6), sign kept.

    Returns the points and, per point, the index of the replaced component (-1: none). Noise
    can push two components just above sin 45°; then the larger is the one replaced.
    """
    raw = np.column_stack([np.asarray(column, dtype=float) for column in (sx, sy, sz)])
    mag = np.abs(raw)
    big = np.argmax(mag, axis=1)
    rows = np.arange(raw.shape[0])
    replaced = np.where(mag[rows, big] > SIN45, big, -1)
    out = raw.copy()
    for component in range(3):
        sel = replaced == component
        if np.any(sel):
            others = np.delete(raw[sel], component, axis=1)
            val = np.sqrt(np.clip(1.0 - np.sum(others**2, axis=1), 0.0, None))
            out[sel, component] = np.where(raw[sel, component] < 0, -val, val)
    return out, replaced


def _noise_gain(
    points: NDArray[np.float64],
    replaced: NDArray[np.intp],
    normal: NDArray[np.float64],
    sigma: float,
) -> NDArray[np.float64]:
    """|∂r/∂(raw outputs)|² of the plane residual r = n·S - sin β: its variance per unit output
    variance.

    A component computed from eq. (6) carries the others' noise scaled by S_other / S_c, which is
    why the direct method's Sz is poor where Sz is near 0 (seed 002 eqs. 14-15). Where S_c² is not
    large against its own noise (about 2σ) the derivative overstates it, so S_c² is floored there.
    """
    grad = np.tile(normal, (points.shape[0], 1))
    for component in range(3):
        sel = replaced == component
        if np.any(sel):
            pc = points[sel, component]
            eff = np.sqrt(pc**2 + 2.0 * sigma + 1e-12)
            for other in range(3):
                if other != component:
                    grad[sel, other] = normal[other] - normal[component] * points[
                        sel, other
                    ] / eff * np.where(pc < 0, -1.0, 1.0)
            grad[sel, component] = 0.0
    gain: NDArray[np.float64] = np.sum(grad**2, axis=1)
    return gain


# --- geometry ------------------------------------------------------------------------------------


def plane_normal(alpha_rad: float, gamma_rad: float) -> NDArray[np.float64]:
    return np.array(
        [
            np.sin(alpha_rad) * np.cos(gamma_rad),
            np.cos(alpha_rad) * np.cos(gamma_rad),
            -np.sin(gamma_rad),
        ]
    )


def fit_plane(points: NDArray[np.float64]) -> tuple[float, float, float]:
    """α, β, γ (radians, β ≥ 0) of the least-squares plane n·S = sin β through the points (eq. 10).

    Minimises Σ (n·S_i - d)² over unit n: the normal is the right singular vector of the
    centred points with the smallest singular value. Refuses points that do not fix the plane.
    """
    n_pts = points.shape[0]
    if n_pts < 3:
        raise DegenerateDataError(
            f"rotation: {n_pts} point(s); eq. (10) needs at least 3 points at different rotation "
            "angles to determine alpha, beta and gamma"
        )
    distinct = np.unique(np.round(points, 12), axis=0).shape[0]
    if distinct < 3:
        raise DegenerateDataError(
            f"rotation: only {distinct} distinct point(s) among {n_pts}; eq. (10) needs the "
            "sensor read at 3 or more different rotation angles"
        )
    centre = points.mean(axis=0)
    _, sv, vt = np.linalg.svd(points - centre, full_matrices=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-300) or sv[0] < 1e-12:
        raise DegenerateDataError(
            "rotation: the points lie on one line (or coincide), so they do not determine the "
            "plane of eq. (10); read the sensor at 3 or more rotation angles spread over the "
            "arc (and check the axis is not vertical)"
        )
    if sv[2] > 0.5 * sv[1]:
        raise DegenerateDataError(
            "rotation: the points scatter as much across the plane of eq. (10) as along it "
            f"(singular values {sv[1]:.3g} and {sv[2]:.3g}); they do not determine the rotation "
            "axis: read more angles over a wider arc, and check that sx, sy, sz are the sines "
            "of one sensor turning about one fixed axis"
        )
    n = vt[2]
    dist = float(n @ centre)
    if dist < 0:
        n, dist = -n, -dist
    gamma = float(np.arcsin(np.clip(-n[2], -1.0, 1.0)))
    alpha = float(np.arctan2(n[0], n[1]))
    beta = float(np.arcsin(np.clip(dist, -1.0, 1.0)))
    return alpha, beta, gamma


def flip_sense(alpha: float, beta: float, gamma: float) -> tuple[float, float, float]:
    """The same plane described with the axis reversed (-L): θ changes sign."""
    alpha_flipped = alpha + np.pi
    alpha_flipped = (alpha_flipped + np.pi) % (2 * np.pi) - np.pi
    return alpha_flipped, -beta, -gamma


def rotation_equations(
    points: NDArray[np.float64], alpha: float, beta: float, gamma: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """sin θ from eq. (7), cos θ from eq. (9), cos θ from eq. (8): each solved for the angle's
    function."""
    sx, sy, sz = points[:, 0], points[:, 1], points[:, 2]
    cb = np.cos(beta)
    sin7 = -(sx * np.cos(alpha) - sy * np.sin(alpha)) / cb
    cos9 = (sz + np.sin(gamma) * np.sin(beta)) / (np.cos(gamma) * cb)
    sg = np.sin(gamma)
    with np.errstate(divide="ignore", invalid="ignore"):
        cos8 = (sx * np.sin(alpha) + sy * np.cos(alpha) - np.cos(gamma) * np.sin(beta)) / (sg * cb)
    return sin7, cos9, cos8


def equation9_region(
    points: NDArray[np.float64], alpha: float, beta: float, gamma: float
) -> NDArray[np.bool_]:
    """Where the paper takes eq. (9): near ±90°, i.e. where |sin θ| > sin 45° (45° < |θ| < 135°)."""
    sin7, cos9, _ = rotation_equations(points, alpha, beta, gamma)
    return np.abs(np.sin(np.arctan2(sin7, cos9))) > SIN45


def theta_switch(
    points: NDArray[np.float64],
    alpha: float,
    beta: float,
    gamma: float,
    use9: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """θ (radians, ±π) by seed 002 §2.3: eq. (9) near ±90° with the sign of sin θ from eq. (7),
    eq. (7) elsewhere with the branch (|θ| < 90° or not) from the sign of cos θ in eq. (9)."""
    sin7, cos9, _ = rotation_equations(points, alpha, beta, gamma)
    if use9 is None:
        use9 = np.abs(np.sin(np.arctan2(sin7, cos9))) > SIN45
    t7 = np.arcsin(np.clip(sin7, -1.0, 1.0))
    t7 = np.where(cos9 < 0, np.copysign(np.pi, t7) - t7, t7)
    t9 = np.arccos(np.clip(cos9, -1.0, 1.0))
    t9 = np.where(sin7 < 0, -t9, t9)
    theta: NDArray[np.float64] = np.where(use9, t9, t7)
    return theta


def theta_combined(
    points: NDArray[np.float64], alpha: float, beta: float, gamma: float
) -> NDArray[np.float64]:
    """θ (radians) minimising |S - S(θ)|²: atan2 of the projections on the circle's two in-plane
    axes.

    e2 = (-cos α, sin α, 0) is eq. (7); e1 = (sin α sin γ, cos α sin γ, cos γ) is eq. (9)·cos γ +
    eq. (8)·sin γ. With γ = 0 this is atan2 of eqs. (7) and (9).
    """
    e1 = np.array([np.sin(alpha) * np.sin(gamma), np.cos(alpha) * np.sin(gamma), np.cos(gamma)])
    e2 = np.array([-np.cos(alpha), np.sin(alpha), 0.0])
    theta: NDArray[np.float64] = np.arctan2(points @ e2, points @ e1)
    return theta


def wrap_deg(x: ArrayLike) -> NDArray[np.float64]:
    return (np.asarray(x, dtype=float) + 180.0) % 360.0 - 180.0


# --- the methods --------------------------------------------------------------------------------


class _RotationMethod:
    kind = "rotation"
    fit_optional = ("theta_ref_deg",)
    correct_optional = ()
    outputs = ("theta_deg", "u_theta_deg")
    uses_sz = True
    estimator = "switch"  # or "combined"
    doc = ""

    def __init__(self, name: str, uses_sz: bool, estimator: str, doc: str):
        self.name = name
        self.uses_sz = uses_sz
        self.estimator = estimator
        self.doc = doc
        self.fit_required = ("sx", "sy", "sz") if uses_sz else ("sx", "sy")
        self.correct_required = self.fit_required

    # points as the method sees them, and which component (if any) it computed from eq. (6)
    def points(self, data: Columns) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
        if self.uses_sz:
            return iodsra_points(data["sx"], data["sy"], data["sz"])
        pts = direct_points(data["sx"], data["sy"])
        return pts, np.full(pts.shape[0], 2)

    def theta(
        self,
        points: NDArray[np.float64],
        alpha: float,
        beta: float,
        gamma: float,
        use9: NDArray[np.bool_] | None = None,
    ) -> NDArray[np.float64]:
        if self.estimator == "combined":
            return theta_combined(points, alpha, beta, gamma)
        return theta_switch(points, alpha, beta, gamma, use9)

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel:
        pts, replaced = self.points(data)
        notes = []
        theta_ref = data.get("theta_ref_deg") if hasattr(data, "get") else None
        (alpha, beta, gamma), sense = self._oriented(pts, fit_plane(pts), theta_ref)
        notes.append(f"axis sense: {sense}")
        _check_not_vertical(beta)
        n = plane_normal(alpha, gamma)
        plane_res = pts @ n - np.sin(beta)
        n_pts = pts.shape[0]
        dof = n_pts - 3
        cov, sigma_s = _plane_covariance(pts, replaced, n, plane_res, alpha, beta, gamma)
        if dof <= 0:
            notes.append(
                "exactly 3 points: the plane is solved, not fitted; no residuals, so no covariance "
                "and no u_theta_deg"
            )
        theta = np.degrees(self.theta(pts, alpha, beta, gamma))
        plane = residual_summary({"plane": plane_res}, "1")
        fit: FitInfo = {
            "n_points": n_pts,
            "dof": dof,
            "sigma_s": sigma_s,
            "plane_residual": plane["columns"]["plane"],
            "estimator": self.estimator,
            "sz_source": "measured (45° rule)" if self.uses_sz else "eq. (6), Sz >= 0",
            "n_replaced_by_eq6": int(np.sum(replaced >= 0)) if self.uses_sz else n_pts,
        }
        if theta_ref is not None:
            res_theta = wrap_deg(theta_ref - theta)  # measured (dividing head) minus model
            residuals = residual_summary({"theta_deg": res_theta}, "deg")
        else:
            residuals = plane
        notes += self._source_notes(sigma_s)
        model = CalibrationModel(
            kind=self.kind,
            method=self.name,
            columns=list(self.fit_required) + (["theta_ref_deg"] if theta_ref is not None else []),
            parameters=_plane_parameters(alpha, beta, gamma),
            covariance_names=list(PARAM_NAMES) if cov is not None else [],
            covariance=cov,
            residuals=residuals,
            fit=fit,
            notes=notes,
            state={"sigma_s": sigma_s},
        )
        if theta_ref is not None and cov is not None:
            self._keep_constant_errors(model, data, np.asarray(theta_ref, dtype=float), theta)
        return model

    def _oriented(
        self,
        pts: NDArray[np.float64],
        plane: tuple[float, float, float],
        theta_ref: NDArray[np.float64] | None,
    ) -> tuple[tuple[float, float, float], str]:
        """The plane's (α, β, γ) in the axis's sense that theta_ref_deg fixes, and which sense."""
        if theta_ref is None:
            return plane, "beta >= 0 (no theta_ref_deg column to fix the sense of the axis)"
        cand = [plane, flip_sense(*plane)]
        rms = [
            float(
                np.sqrt(np.mean(wrap_deg(np.degrees(self.theta(pts, *candidate)) - theta_ref) ** 2))
            )
            for candidate in cand
        ]
        return (cand[1] if rms[1] < rms[0] else plane), (
            "the sense of the axis that reproduces theta_ref_deg"
        )

    def _source_notes(self, sigma_s: float | None) -> list[str]:
        """What the notes say of where the method's Sz and the output noise come from."""
        notes = []
        if not self.uses_sz:
            notes.append(
                "direct method: Sz from eq. (6) taken as >= 0; angles where the sensor normal "
                "points below the horizontal (true Sz < 0) are measured wrongly"
            )
        if sigma_s is not None:
            notes.append(
                f"output noise sigma_s = {sigma_s:.3g} (sine units) from the plane residuals, "
                "used for u_theta_deg"
            )
        return notes

    def _keep_constant_errors(
        self,
        model: CalibrationModel,
        data: Columns,
        ref: NDArray[np.float64],
        theta: NDArray[np.float64],
    ) -> None:
        """Keep the per-branch θ bias of the outputs' constant errors the dividing head shows."""
        const = self.constant_errors(model, data, ref, wrap_deg(ref - theta))
        if const is not None:
            model.state[CONSTANT_ERRORS_KEY] = const
            model.notes.append(
                "constant output errors (zero offsets, scale errors of sx, sy, sz) bias "
                "theta by an amount that depends on the angle, jumps where the method "
                "changes branch and does not show in the output scatter: per branch, a "
                "straight line through the theta residuals against theta_ref_deg gives it "
                "per angle; its square (the bias's square and its estimation variance) adds "
                "to u_theta_deg (largest residual "
                f"{float(np.max(np.abs(wrap_deg(ref - theta)))):.3g} deg)"
            )

    def theta_deg(self, model: CalibrationModel, data: Columns) -> NDArray[np.float64]:
        alpha, beta, gamma = np.radians(model.values(PARAM_NAMES))
        pts, _ = self.points(data)
        return np.degrees(self.theta(pts, alpha, beta, gamma))

    def _fit_uncertainty(
        self, model: CalibrationModel, data: Columns, readings: bool = True
    ) -> tuple[NDArray[np.float64], Propagated | None]:
        """θ and its propagated standard uncertainty from the plane fit and the output noise (the
        plane's parameters alone with `readings=False`; None without a covariance)."""
        p0 = model.values(PARAM_NAMES)
        alpha, beta, gamma = np.radians(p0)
        pts, _ = self.points(data)
        use9 = equation9_region(pts, alpha, beta, gamma)
        theta0 = np.degrees(self.theta(pts, alpha, beta, gamma, use9))
        sigma = model.state.get("sigma_s") if isinstance(model.state, Mapping) else None
        if model.covariance is None or sigma is None:
            return theta0, None
        inputs = {column: np.asarray(data[column], dtype=float) for column in self.fit_required}

        def f(p: NDArray[np.float64], x: Mapping[str, NDArray[np.float64]]) -> NDArray[np.float64]:
            pp, _ = self.points(x)
            pa, pb, pg = np.radians(p)
            t = np.degrees(self.theta(pp, pa, pb, pg, use9))
            return theta0 + wrap_deg(t - theta0)  # no jump at ±180° inside the differences

        dof = float(model.fit.get("dof") or np.inf)  # cov and sigma_s both from the plane residuals
        return theta0, propagate_gum(
            f,
            p0,
            model.cov_of(list(PARAM_NAMES)),
            inputs,
            {column: float(sigma) for column in self.fit_required} if readings else None,
            dof,
            dof,
        )

    def _parameter_part(self, model: CalibrationModel, data: Columns) -> NDArray[np.float64]:
        """The standard uncertainty θ has from the plane's parameters alone, per angle (called
        only where the model has a covariance)."""
        _, propagated = self._fit_uncertainty(model, data, readings=False)
        assert propagated is not None
        return propagated.u

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, NDArray[np.float64]]:
        theta0, propagated = self._fit_uncertainty(model, data)
        out = {"theta_deg": theta0}
        if propagated is not None:
            const = model.state.get(CONSTANT_ERRORS_KEY)
            # the outputs' constant errors, seen in the fit's θ residuals against the dividing head
            if const:
                out["u_theta_deg"], out["k_theta"] = self._with_constant_errors(
                    model, data, theta0, propagated
                )
                return out
            out["u_theta_deg"] = propagated.expanded()
            out["k_theta"] = coverage_factor(propagated.dof_eff)
        return out

    def _with_constant_errors(
        self,
        model: CalibrationModel,
        data: Columns,
        theta0: NDArray[np.float64],
        propagated: Propagated,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(U, k) of θ with the bias the arcs' lines show against the dividing head.

        A line's value b̂ at an angle holds this model's whole θ error there (the outputs' constant
        errors and the plane's own error, since the plane was fitted without theta_ref_deg) and its
        estimation error (variance v). Where the line says little beyond its own noise
        (|b̂| ≤ 2√v), b̂² − v (which estimates b²) counts as a variance beside the propagated u.
        Where it shows a bias (|b̂| > 2√v: the `direct` method's, whose plane error its
        linearised u understates), that bias is known but not corrected: U is the 95 % interval
        about zero of an error near it (`expanded_with_bias`), with the reading's own noise and
        v as the random part; k·√(b² + u²) would hold an error sitting at the bias every time."""
        bias, bias_var = self.constant_errors_bias(model, data, theta0)
        dof = float(model.fit.get("dof") or np.inf)
        # the bias's square as a variance: b̂² − v estimates b² (the estimation error is not in the
        # error of a θ the line does not correct)
        size2 = np.maximum(bias**2 - bias_var, 0.0)
        nu = welch_satterthwaite([(propagated.u**2, dof), (size2, dof)])
        k_quadrature = coverage_factor(nu)
        u_quadrature = np.sqrt(propagated.u**2 + size2)
        # a known bias: the parameters' part is in the line already
        noise2 = np.maximum(propagated.u**2 - self._parameter_part(model, data) ** 2, 0.0)
        nu_random = welch_satterthwaite([(noise2, dof), (bias_var, dof)])
        known = np.sign(bias) * np.sqrt(size2)
        u_biased, k_biased = expanded_with_bias(
            known, np.sqrt(noise2 + bias_var), coverage_factor(nu_random)
        )
        shows_bias = np.abs(bias) > 2.0 * np.sqrt(bias_var)
        return (
            np.where(shows_bias, u_biased, k_quadrature * u_quadrature),
            np.where(shows_bias, k_biased, k_quadrature),
        )

    def regimes(
        self, model: CalibrationModel, data: Columns, theta_deg: NDArray[np.float64]
    ) -> list[str]:
        """Which branch of the method serves each point: the component the 45° rule replaced and,
        for the switch, the equation taken. The bias from constant output errors jumps where the
        branch changes."""
        alpha, beta, gamma = np.radians(model.values(PARAM_NAMES))
        pts, replaced = self.points(data)
        use9 = (
            equation9_region(pts, alpha, beta, gamma)
            if self.estimator == "switch"
            else np.zeros(pts.shape[0], dtype=bool)
        )
        return [f"{int(component)}{'9' if eq9 else '7'}" for component, eq9 in zip(replaced, use9)]

    def constant_errors(
        self,
        model: CalibrationModel,
        data: Columns,
        theta_ref_deg: NDArray[np.float64],
        res_theta_deg: NDArray[np.float64],
    ) -> list[ConstantErrorArc] | None:
        """How the outputs' constant errors (zero offsets, scale errors) bias θ, seen against the
        dividing head.

        They bend the points off the circle in a way the fitted plane absorbs only in part, so θ is
        biased by an amount that depends on the angle, jumps where the method changes branch (the
        45° rule, the switch between equations) and does not show in the output scatter. The fit's θ
        residuals against theta_ref_deg hold it: per arc of one branch, a straight line in θ through
        that arc's residuals (their mean where it has two points or fewer) gives each angle's bias.
        None where the points are too few to tell (fewer than 8).
        """
        if res_theta_deg.size < 8:
            return None
        _, propagated = self._fit_uncertainty(model, data)
        # the residuals' scatter about an arc's line as the fit propagates it: the readings' own
        # noise, not the parameters' part (smooth along the arc, it is in the line)
        noise2 = (
            np.zeros(res_theta_deg.size)
            if propagated is None
            else np.maximum(propagated.u**2 - self._parameter_part(model, data) ** 2, 0.0)
        )
        order = np.argsort(wrap_deg(theta_ref_deg))
        regime = np.array(self.regimes(model, data, theta_ref_deg))[order]
        t_all, r_all, n_all = wrap_deg(theta_ref_deg)[order], res_theta_deg[order], noise2[order]
        return [
            _arc_line(str(regime[idx[0]]), t_all[idx], r_all[idx], n_all[idx])
            for idx in _branch_arcs(regime, t_all)
        ]

    def constant_errors_bias(
        self, model: CalibrationModel, data: Columns, theta_deg: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Per corrected angle, the θ bias the arcs' lines show against the dividing head (measured
        minus model: the outputs' constant errors and the plane's own error) and its estimate's
        variance, from the arc of the angle's branch that
        holds it (or is nearest, extrapolated no further than its half-width). A branch the
        calibration never used: no bias known, the largest square any arc showed as a variance."""
        arcs = model.state.get(CONSTANT_ERRORS_KEY) or []
        bias = np.full(theta_deg.shape, np.nan)
        var = np.full(theta_deg.shape, np.nan)
        regime = np.array(self.regimes(model, data, theta_deg))
        best = np.full(theta_deg.shape, np.inf)
        worst = 0.0
        for arc in arcs:
            coef = np.asarray(arc["coefficients_deg"], dtype=float)
            coef_cov = np.asarray(arc["coefficient_covariance_deg2"], dtype=float)
            centre, half = float(arc["centre_deg"]), float(arc["half_width_deg"])
            offset = wrap_deg(theta_deg - centre)
            design = _local(np.clip(offset, -half, half) + centre, centre, linear=coef.size == 2)
            arc_bias = design @ coef
            arc_var = np.einsum("ij,jk,ik->i", design, coef_cov, design)
            dist = np.abs(offset)
            take = (regime == arc["branch"]) & (dist < best)
            bias[take], var[take], best[take] = arc_bias[take], arc_var[take], dist[take]
            worst = max(worst, float(np.max(arc_bias**2 + arc_var, initial=0.0)))
        unseen = np.isnan(bias)
        bias[unseen], var[unseen] = 0.0, worst
        return bias, var


def _branch_arcs(regime: NDArray[np.str_], t_sorted: NDArray[np.float64]) -> list[list[int]]:
    """The runs of one branch along the sorted angles (indices), the circle closed across ±180°."""
    starts = [0] + [i for i in range(1, regime.size) if regime[i] != regime[i - 1]]
    arcs = [list(range(start, stop)) for start, stop in zip(starts, starts[1:] + [regime.size])]
    # the circle closes: one arc across ±180°
    if len(arcs) > 1 and regime[0] == regime[-1] and np.ptp(t_sorted) > 300:
        arcs[0] = arcs.pop() + arcs[0]
    return arcs


def _arc_line(
    branch: str, t: NDArray[np.float64], residual: NDArray[np.float64], noise2: NDArray[np.float64]
) -> ConstantErrorArc:
    """One arc's θ bias for MODEL.json: a line in θ about the arc's centre, and its covariance."""
    centre = float(
        np.degrees(np.arctan2(np.mean(np.sin(np.radians(t))), np.mean(np.cos(np.radians(t)))))
    )
    design = _local(t, centre, linear=t.size >= 3)
    coef, *_ = np.linalg.lstsq(design, residual, rcond=None)
    dof = t.size - design.shape[1]
    # the scatter about the line: the propagated noise, or the residuals' own where they have
    # enough degrees of freedom and say more (the dividing head's noise, which the fit does not
    # know)
    s2 = float(np.mean(noise2))
    if dof >= 3:
        s2 = float(np.sum((residual - design @ coef) ** 2) / dof)
    half = float(np.max(np.abs(wrap_deg(t - centre))))
    return {
        "branch": branch,
        "centre_deg": centre,
        "half_width_deg": half,
        "coefficients_deg": coef.tolist(),
        "coefficient_covariance_deg2": (s2 * np.linalg.pinv(design.T @ design)).tolist(),
    }


def _check_not_vertical(beta: float) -> None:
    """Refuse a vertical axis: turning about it does not change the tilt, so θ is not measured."""
    if not np.isfinite(beta) or abs(np.cos(beta)) < 1e-6:
        raise DegenerateDataError(
            "rotation: the fitted axis is vertical (beta = ±90°): turning about it does not "
            "change the tilt, so θ cannot be measured"
        )


def _plane_covariance(
    pts: NDArray[np.float64],
    replaced: NDArray[np.intp],
    n: NDArray[np.float64],
    plane_res: NDArray[np.float64],
    alpha: float,
    beta: float,
    gamma: float,
) -> tuple[NDArray[np.float64] | None, float | None]:
    """The covariance of (α, β, γ) in degrees and the output noise σ_s; (None, None) at 3 points."""
    n_pts = pts.shape[0]
    dof = n_pts - 3
    if dof <= 0:
        return None, None
    sigma_guess = float(np.sqrt(np.sum(plane_res**2) / dof))
    gain = _noise_gain(pts, replaced, n, sigma_guess)
    # once more with the noise the gains imply
    gain = _noise_gain(pts, replaced, n, float(np.sqrt(np.sum(plane_res**2 / gain) / dof)))
    # Jacobian of the plane residual wrt (α, β, γ) in degrees
    dn_da = np.array([np.cos(alpha) * np.cos(gamma), -np.sin(alpha) * np.cos(gamma), 0.0])
    dn_dg = np.array(
        [-np.sin(alpha) * np.sin(gamma), -np.cos(alpha) * np.sin(gamma), -np.cos(gamma)]
    )
    jacobian = np.column_stack([pts @ dn_da, np.full(n_pts, -np.cos(beta)), pts @ dn_dg]) * (
        np.pi / 180.0
    )
    sigma_s = float(np.sqrt(np.sum(plane_res**2 / gain) / dof))
    jtj = jacobian.T @ jacobian
    if np.linalg.cond(jtj) > 1e14:
        raise DegenerateDataError(
            "rotation: the points do not separate alpha, beta and gamma (the normal "
            "equations are singular); read the sensor over a wider arc"
        )
    inv = np.linalg.inv(jtj)
    # sandwich: per-point variance
    cov = inv @ (jacobian.T @ (jacobian * (sigma_s**2 * gain)[:, None])) @ inv
    return 0.5 * (cov + cov.T), sigma_s


def _plane_parameters(alpha: float, beta: float, gamma: float) -> dict[str, Parameter]:
    """The plane's angles (radians) as the model's parameters in degrees, each saying what it is."""
    values = np.degrees([alpha, beta, gamma])
    return {
        "alpha_deg": Parameter(
            float(values[0]),
            "deg",
            note="angle between the y axis and L's projection on the sensor plane",
        ),
        "beta_deg": Parameter(
            float(values[1]), "deg", note="inclination of the rotation axis L to the horizontal"
        ),
        "gamma_deg": Parameter(
            float(values[2]), "deg", note="angle between L and the sensor plane"
        ),
    }


DIRECT = _RotationMethod(
    "direct",
    uses_sz=False,
    estimator="switch",
    doc="seed 002 §2.1: Sz from eq. (6) (Sz >= 0), θ by eqs. (7)/(9)",
)
IODSRA = _RotationMethod(
    "iodsra",
    uses_sz=True,
    estimator="switch",
    doc="seed 002 §2.2-2.3: measured Sz with the 45° rule, θ by eqs. (7)/(9)",
)
IODSRA_COMBINED = _RotationMethod(
    "iodsra-combined",
    uses_sz=True,
    estimator="combined",
    doc="IODSRA points, θ = least-squares angle on the circle (eqs. 7-9 together)",
)
