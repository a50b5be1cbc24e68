"""A bench model as a baseline plus named effect terms, fitted by weighted least squares.

A family (stage/linear, stage/kinematic, scale/poly) says which parameters each effect adds
(in the effect's own units, names from the registry where it has them) and how the model
predicts the readings; this module does the fitting, the covariance, and the check that a
term is separable from what the model already holds on the data at hand.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from service.calibration.differences import central_jacobian
from service.discrepancy.report_types import Magnitude
from service.errors import DegenerateDataError, FitError


@dataclass(frozen=True)
class Block:
    """The parameters one effect (or the baseline) adds to the model."""

    effect: str  # "baseline" for the baseline's own parameters
    labels: tuple[str, ...]
    units: tuple[str, ...]
    scales: tuple[float, ...]  # typical magnitudes: solver scaling and finite-difference steps
    init: tuple[float, ...]

    @property
    def size(self) -> int:
        return len(self.labels)


@dataclass
class Fit:
    """A fitted model: parameter values, covariance, residuals (observed - predicted) per axis."""

    effects: tuple[str, ...]
    blocks: list[Block]
    values: NDArray[np.float64]
    covariance: NDArray[np.float64]
    residuals: NDArray[np.float64]  # (N, A) in the data's unit
    predicted: NDArray[np.float64]  # (N, A)
    rss_w: float  # noise-weighted residual sum of squares
    n_obs: int
    jacobian_w: NDArray[np.float64] = field(repr=False, default_factory=lambda: np.zeros((0, 0)))

    @property
    def k(self) -> int:
        return int(self.values.size)

    @property
    def dof(self) -> int:
        return self.n_obs - self.k

    def block_slice(self, effect: str, occurrence: int = 0) -> slice:
        i, seen = 0, 0
        for block in self.blocks:
            if block.effect == effect:
                if seen == occurrence:
                    return slice(i, i + block.size)
                seen += 1
            i += block.size
        raise KeyError(effect)

    def block(self, effect: str, occurrence: int = 0) -> Block:
        seen = 0
        for candidate in self.blocks:
            if candidate.effect == effect:
                if seen == occurrence:
                    return candidate
                seen += 1
        raise KeyError(effect)

    def rms(self) -> list[float]:
        return [
            float(np.sqrt(np.mean(self.residuals[:, axis] ** 2)))
            for axis in range(self.residuals.shape[1])
        ]


class Family:
    """Baseline + candidate terms of one data kind. Subclasses define `blocks` and `predict`."""

    kind: str = ""
    baseline: str = ""
    unit: str = ""
    axes: tuple[str, ...] = ()
    # per candidate: what would let data like these show it, said when the model barely sees it
    separability_hints: dict[str, str] = {}

    def __init__(self, observed: NDArray[np.float64], weights: NDArray[np.float64]):
        self.observed = np.asarray(observed, dtype=float).reshape(len(observed), -1)
        self.weights = np.asarray(weights, dtype=float)
        # per effect, the parameters the data can separate (all when absent)
        self.active: dict[str, tuple[str, ...]] = {}
        # with a known noise level the weighted residual has unit variance; otherwise the
        # covariance is scaled by the residual variance of the fit
        self.noise_known = False

    # -- to be provided by a family ------------------------------------------------------------
    def full_blocks(self, effects: tuple[str, ...]) -> list[Block]:
        """Every parameter the effects could add, before dropping what the data cannot separate."""
        raise NotImplementedError

    def predict_params(
        self, effects: tuple[str, ...], params: dict[str, dict[str, float]]
    ) -> NDArray[np.float64]:
        """Noise-free readings (N, A); a parameter missing from `params` means its effect-free
        value."""
        raise NotImplementedError

    def magnitude(self, fit: Fit, effect: str) -> Magnitude:
        """The fitted size of an effect in its own units, with standard uncertainties."""
        raise NotImplementedError

    # -- parameters --------------------------------------------------------------------------------
    def blocks(self, effects: tuple[str, ...]) -> list[Block]:
        out = []
        for block in self.full_blocks(effects):
            keep = self.active.get(block.effect)
            if keep is not None:
                idx = [i for i, lab in enumerate(block.labels) if lab in keep]
                block = Block(
                    block.effect,
                    tuple(block.labels[i] for i in idx),
                    tuple(block.units[i] for i in idx),
                    tuple(block.scales[i] for i in idx),
                    tuple(block.init[i] for i in idx),
                )
            out.append(block)
        return out

    @staticmethod
    def unpack(blocks: list[Block], theta: NDArray[np.float64]) -> dict[str, dict[str, float]]:
        params: dict[str, dict[str, float]] = {}
        i = 0
        for block in blocks:
            values = params.setdefault(block.effect, {})
            for lab in block.labels:
                values[lab] = float(theta[i])
                i += 1
        return params

    def predict(
        self,
        effects: tuple[str, ...],
        theta: NDArray[np.float64],
        blocks: list[Block] | None = None,
    ) -> NDArray[np.float64]:
        return self.predict_params(effects, self.unpack(blocks or self.blocks(effects), theta))

    def initial(
        self, effects: tuple[str, ...], blocks: list[Block], start: Fit | None
    ) -> NDArray[np.float64]:
        """Start values: the previous fit's values where the parameter is the same, block init
        elsewhere."""
        x = (
            np.concatenate([np.asarray(block.init, dtype=float) for block in blocks])
            if blocks
            else np.zeros(0)
        )
        if start is None:
            return x
        i = 0
        prev = {}
        j = 0
        for block in start.blocks:
            for lab in block.labels:
                prev[(block.effect, lab)] = start.values[j]
                j += 1
        for block in blocks:
            for lab in block.labels:
                if (block.effect, lab) in prev:
                    x[i] = prev[(block.effect, lab)]
                i += 1
        return x

    # -- generic machinery ---------------------------------------------------------------------
    @property
    def n_obs(self) -> int:
        return int(self.observed.size)

    def weighted_residual(
        self,
        effects: tuple[str, ...],
        theta: NDArray[np.float64],
        blocks: list[Block] | None = None,
    ) -> NDArray[np.float64]:
        residual: NDArray[np.float64] = (
            (self.observed - self.predict(effects, theta, blocks)) * self.weights
        ).ravel()
        return residual

    def fit(
        self,
        effects: tuple[str, ...],
        start: Fit | None = None,
        x0: NDArray[np.float64] | None = None,
    ) -> Fit:
        blocks = self.blocks(effects)
        k = sum(block.size for block in blocks)
        if self.n_obs <= k:
            raise DegenerateDataError(
                f"{self.n_obs // max(self.observed.shape[1], 1)} points give {self.n_obs} "
                f"readings, not more than the {k} parameters of the model "
                f"({self.baseline} + {', '.join(effects) or 'nothing'})"
            )
        theta0 = self.initial(effects, blocks, start) if x0 is None else np.asarray(x0, dtype=float)
        scales = np.concatenate([np.asarray(block.scales, dtype=float) for block in blocks])

        def fun(q: NDArray[np.float64]) -> NDArray[np.float64]:
            return self.weighted_residual(effects, q * scales, blocks)

        q0 = theta0 / scales
        with np.errstate(all="ignore"):
            r0 = fun(q0)
        if not np.all(np.isfinite(r0)):
            raise FitError(
                f"model {self.baseline} + {', '.join(effects)} cannot be evaluated at its start "
                "values"
            )
        try:
            sol = least_squares(
                fun, q0, method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200 * (k + 1)
            )
        except ValueError as exc:  # pragma: no cover - scipy refuses e.g. non-finite residuals
            raise FitError(f"fit of {self.baseline} + {', '.join(effects)} failed: {exc}") from exc
        if not np.all(np.isfinite(sol.x)):
            raise FitError(f"fit of {self.baseline} + {', '.join(effects)} diverged")
        theta = sol.x * scales
        # d(weighted residual)/d(theta), by the shared rule
        jacobian = self.jacobian(effects, blocks, theta)
        pred = self.predict(effects, theta, blocks)
        resid = self.observed - pred
        rss_w = float(np.sum((resid * self.weights) ** 2))
        s2 = rss_w / max(self.n_obs - k, 1)
        # known noise: the noise variance, raised (Birge ratio) if the residual says it is larger
        cov = _covariance(jacobian) * (max(1.0, s2) if self.noise_known else s2)
        return Fit(tuple(effects), blocks, theta, cov, resid, pred, rss_w, self.n_obs, jacobian)

    def jacobian(
        self,
        effects: tuple[str, ...],
        blocks: list[Block],
        theta: NDArray[np.float64],
        columns: range | None = None,
    ) -> NDArray[np.float64]:
        """Jacobian of the weighted residual, d r / d theta (selected columns), by the shared
        rule."""
        scales = np.concatenate([np.asarray(block.scales, dtype=float) for block in blocks])
        cols = np.arange(theta.size) if columns is None else np.asarray(list(columns), dtype=int)
        if cols.size == 0:
            return np.zeros((self.n_obs, 0))

        def fun(sub: NDArray[np.float64]) -> NDArray[np.float64]:
            t = theta.copy()
            t[cols] = sub
            return self.weighted_residual(effects, t, blocks)

        return central_jacobian(fun, theta[cols], scales[cols])

    def extended(
        self, current: Fit, effect: str, full: bool = False
    ) -> tuple[tuple[str, ...], list[Block], NDArray[np.float64]]:
        """Effects, blocks and start values of the current model plus `effect` (all its parameters
        if `full`)."""
        effects = current.effects + (effect,)
        if full:
            new = [
                full_block
                for full_block in self.full_blocks(effects)
                if full_block.effect == effect
            ][-1:]
            blocks = self.blocks(current.effects) + new
        else:
            blocks = self.blocks(effects)
        return effects, blocks, self.initial(effects, blocks, current)

    def linearised_fit(self, current: Fit, effect: str) -> Fit:
        """The extended model after one Gauss-Newton step from its start values (an approximate
        fit).

        A cheap and, near the current optimum, accurate preview of the full refit: used to
        screen candidates so that only promising ones pay for a nonlinear fit, and to state
        the size of a candidate the data do not support (its value and uncertainty).
        """
        effects, blocks, theta = self.extended(current, effect)
        r0 = self.weighted_residual(effects, theta, blocks)
        k0 = current.k
        same_start = (
            theta.size > k0
            and np.array_equal(theta[:k0], current.values)
            and current.jacobian_w.shape == (r0.size, k0)
        )
        if same_start:
            # the current model's columns are unchanged: reuse them
            J_new = self.jacobian(effects, blocks, theta, range(k0, theta.size))
            jacobian = np.column_stack([current.jacobian_w, J_new])
        else:
            jacobian = self.jacobian(effects, blocks, theta)
        delta, *_ = np.linalg.lstsq(jacobian, -r0, rcond=1e-12)
        r1 = r0 + jacobian @ delta
        if r1 @ r1 > r0 @ r0:
            delta, r1 = np.zeros_like(delta), r0
        rss_w = float(r1 @ r1)
        s2 = rss_w / max(self.n_obs - theta.size, 1)
        cov = _covariance(jacobian) * (max(1.0, s2) if self.noise_known else s2)
        resid = r1.reshape(self.observed.shape) / self.weights
        return Fit(
            effects,
            blocks,
            theta + delta,
            cov,
            resid,
            self.observed - resid,
            rss_w,
            self.n_obs,
            jacobian,
        )

    def separability(self, current: Fit, effect: str) -> list[float]:
        """For each parameter of `effect`: the fraction of its signature the current model cannot
        absorb.

        The signature is the column of the (weighted) Jacobian at the current fit; the
        fraction is the norm of its component orthogonal to the current model's columns over
        its own norm. Zero means the data cannot tell the term from what is fitted already.
        """
        effects, blocks, theta = self.extended(current, effect, full=True)
        n0 = theta.size - blocks[-1].size
        if np.array_equal(theta[:n0], current.values) and current.jacobian_w.shape[1] == n0:
            Jm = current.jacobian_w
            Jc = self.jacobian(effects, blocks, theta, range(n0, theta.size))
        else:
            jacobian = self.jacobian(effects, blocks, theta)
            Jm, Jc = jacobian[:, :n0], jacobian[:, n0:]
        if Jm.size:
            basis, singular, _ = np.linalg.svd(Jm, full_matrices=False)
            basis = (
                basis[:, singular > 1e-10 * singular[0]]
                if singular.size and singular[0] > 0
                else basis[:, :0]
            )
        out = []
        for column in Jc.T:
            nc = float(np.linalg.norm(column))
            if nc == 0.0 or not np.isfinite(nc):
                out.append(0.0)
                continue
            rest = column - basis @ (basis.T @ column) if Jm.size else column
            out.append(float(np.linalg.norm(rest) / nc))
        return out


def _covariance(J: NDArray[np.float64]) -> NDArray[np.float64]:
    """(JᵀJ)⁻¹ of the weighted problem; pseudo-inverse where a direction is not determined."""
    if J.size == 0:
        return np.zeros((0, 0))
    JtJ = J.T @ J
    scale = np.sqrt(np.maximum(np.diag(JtJ), 1e-300))
    cov_scaled = np.linalg.pinv(JtJ / np.outer(scale, scale), rcond=1e-12)
    cov: NDArray[np.float64] = cov_scaled / np.outer(scale, scale)
    return cov
