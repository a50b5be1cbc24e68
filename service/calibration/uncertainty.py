"""GUM law of propagation of uncertainty (JCGM 100 §5) for corrected values.

The measurand y = f(p, x) depends on fitted parameters p (covariance from the fit) and
the readings x (independent white noise). Sensitivities are central differences, vectorised
over points; expanded uncertainty U = k · u_c with k from Student's t at the Welch-Satterthwaite
effective degrees of freedom (JCGM 100 G.4), for a 95 % coverage interval.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special

from service.calibration.differences import fd_step

COVERAGE = 0.95  # coverage probability of the expanded uncertainties


def _step(value: ArrayLike, variance: float) -> NDArray[np.float64]:
    """The finite-difference rule (service.calibration.differences) with the quantity's own standard
    uncertainty as its scale: the step is at least a thousandth of it (1e-6 x 1000 u)."""
    return fd_step(value, 1e3 * np.sqrt(max(float(variance), 0.0)))


@dataclass
class Propagated:
    """Combined standard uncertainty u_c of each output and its Welch-Satterthwaite degrees of
    freedom."""

    u: NDArray[np.float64]
    dof_eff: NDArray[np.float64]

    def expanded(self, coverage: float = COVERAGE) -> NDArray[np.float64]:
        """U = k·u_c with k the t quantile for the effective degrees of freedom (JCGM 100 G.4,
        G.6.4)."""
        return coverage_factor(self.dof_eff, coverage) * self.u


def coverage_factor(dof_eff: ArrayLike, coverage: float = COVERAGE) -> NDArray[np.float64]:
    """k for a two-sided coverage interval: Student's t at `dof_eff` degrees of freedom (normal at
    infinity).

    A fixed k = 2 covers about 95 % only for many degrees of freedom: at 10 it covers 92.7 %.
    """
    nu = np.asarray(dof_eff, dtype=float)
    prob = 0.5 + coverage / 2.0
    if nu.size > _TABLE_ABOVE and np.all(nu >= 1.0):
        # one value per corrected reading: interpolated in 1/ν on a fine table (relative error below
        # 1e-7), since the exact inverse costs microseconds per value and correct handles 10^5-10^6
        # readings
        grid, k = _coverage_table(prob)
        k_nu: NDArray[np.float64] = np.interp(1.0 / nu, grid, k)
        return k_nu
    # scipy.special's inverse t (scipy.stats would add a slow import to every command-line start)
    return np.asarray(special.stdtrit(nu, prob))


_TABLE_ABOVE = 256


def dof_of_coverage_factor(k: ArrayLike, coverage: float = COVERAGE) -> NDArray[np.float64]:
    """The degrees of freedom ν whose Student's t factor is k (coverage_factor's inverse; infinite
    at the normal's)."""
    kk = np.asarray(k, dtype=float)
    prob = 0.5 + coverage / 2.0
    normal = float(special.ndtri(prob))
    with np.errstate(all="ignore"):
        nu = special.stdtridf(prob, np.maximum(kk, normal))
    return np.asarray(np.where(kk <= normal * (1 + 1e-9), np.inf, nu), dtype=float)


@functools.lru_cache(maxsize=4)
def _coverage_table(q: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Student's t quantile q tabulated on 1/ν in [0, 1] (ν from infinity down to 1)."""
    grid = np.linspace(0.0, 1.0, 4001)
    with np.errstate(divide="ignore"):
        k = special.stdtrit(1.0 / grid, q)
    k[0] = special.ndtri(q)
    return grid, k


def welch_satterthwaite(
    components: Sequence[tuple[ArrayLike, float]],
    *,
    same_dof_shared: bool = True,
) -> NDArray[np.float64]:
    """ν_eff = u_c⁴ / Σ u_i⁴ / ν_i over the variance components (u_i², ν_i) (JCGM 100 eq. G.2b).

    Components given the same finite ν rest on one estimated standard deviation (one fit's σ̂, as
    the parameters' covariance and the reading noise of a corrected value do): they are one estimate
    with that ν, not independent ones, so their variances are summed before the formula (which would
    otherwise give more degrees of freedom than the fit has). With `same_dof_shared` false every
    component is its own estimate (two sensors' noises, each from its own readings). Infinite where
    every component with a finite ν is zero (or u_c is zero).
    """
    finite = [
        (np.asarray(variance, dtype=float), nu) for variance, nu in components if np.isfinite(nu)
    ]
    if same_dof_shared:
        groups: dict[float, NDArray[np.float64]] = {}
        for variance, nu in finite:
            groups[nu] = groups.get(nu, 0.0) + variance
        finite = [(variance, nu) for nu, variance in groups.items()]
    total = sum(np.asarray(variance, dtype=float) for variance, _ in components)
    denom = sum(variance**2 / nu for variance, nu in finite)
    with np.errstate(divide="ignore", invalid="ignore"):
        nu_eff = np.where(
            np.asarray(denom) > 0,
            np.asarray(total) ** 2 / np.where(np.asarray(denom) > 0, denom, 1.0),
            np.inf,
        )
    return np.asarray(nu_eff, dtype=float)


def propagate(
    f: Callable[[NDArray[np.float64], Mapping[str, NDArray[np.float64]]], ArrayLike],
    params: NDArray[np.float64],
    cov: NDArray[np.float64] | None,
    inputs: Mapping[str, NDArray[np.float64]],
    input_sigma: Mapping[str, float] | None = None,
) -> NDArray[np.float64]:
    """Standard uncertainty of each output of f.

    `f(p, inputs)` returns an array (N,) or (N, m). Returns the same shape: combined standard
    uncertainty u_c from the parameter covariance and the input noise (no correlation between
    the two, which holds when the readings being corrected are not the calibration data).
    """
    return propagate_gum(f, params, cov, inputs, input_sigma).u


def propagate_gum(
    f: Callable[[NDArray[np.float64], Mapping[str, NDArray[np.float64]]], ArrayLike],
    params: NDArray[np.float64],
    cov: NDArray[np.float64] | None,
    inputs: Mapping[str, NDArray[np.float64]],
    input_sigma: Mapping[str, float] | None = None,
    params_dof: float = np.inf,
    inputs_dof: float = np.inf,
) -> Propagated:
    """propagate() with the effective degrees of freedom of each output.

    The parameters' contribution J·cov·Jᵀ is one component with `params_dof` (the fit's degrees
    of freedom); each input's (c_i σ_i)² is one with `inputs_dof` (those of the σ estimate:
    infinite for a noise level known beforehand).
    """
    params = np.asarray(params, dtype=float)
    y0 = np.asarray(f(params, inputs), dtype=float)
    components: list[tuple[NDArray[np.float64], float]] = []
    if cov is not None and params.size:
        jac = []
        for i in range(params.size):
            step = _step(params[i], cov[i][i])
            pp, pm = params.copy(), params.copy()
            pp[i] += step
            pm[i] -= step
            jac.append((np.asarray(f(pp, inputs)) - np.asarray(f(pm, inputs))) / (2 * step))
        jacobian = np.stack(jac, axis=-1)  # (..., n_params)
        components.append(
            (np.einsum("...i,ij,...j->...", jacobian, np.asarray(cov), jacobian), params_dof)
        )
    for name, sigma in (input_sigma or {}).items():
        if not sigma:
            continue
        x = np.asarray(inputs[name], dtype=float)
        step = _step(x, sigma**2)
        up = dict(inputs)
        dn = dict(inputs)
        up[name] = x + step
        dn[name] = x - step
        sensitivity = (np.asarray(f(params, up)) - np.asarray(f(params, dn))) / (
            2 * step if y0.ndim == 1 else (2 * step)[:, None]
        )
        components.append(((sensitivity * sigma) ** 2, inputs_dof))
    var = sum((variance for variance, _ in components), np.zeros_like(y0))
    return Propagated(
        np.sqrt(var), welch_satterthwaite(components) if components else np.full(y0.shape, np.inf)
    )


@dataclass(frozen=True)
class MeanTypeA:
    """The mean of n readings and its Type A standard uncertainty (JCGM 100 4.2), allowing for their
    correlation."""

    mean: float
    u: float  # s / √n_eff
    dof: float  # n_eff − 1, at least 1
    n: int
    n_eff: float  # the number of independent readings they are worth
    lag1: float  # the readings' lag-1 autocorrelation, as estimated (≥ 0 used)


def mean_type_a(values: ArrayLike) -> MeanTypeA:
    """Mean of a series of readings with the standard uncertainty of that mean.

    Readings of a sensor close in time are not always independent (filtering, a slow wander): s/√n
    would then understate the mean's uncertainty. With the lag-1 autocorrelation ρ of an AR(1)
    series the mean is worth n_eff = n (1 − ρ)/(1 + ρ) independent readings (never more than n: a
    negative ρ is taken as 0), and u = s/√n_eff with n_eff − 1 degrees of freedom. Needs two
    readings or more."""
    readings = np.asarray(values, dtype=float)
    n = int(readings.size)
    if n < 2:
        raise ValueError(f"a mean's Type A uncertainty needs two readings or more, got {n}")
    mean = float(readings.mean())
    deviations = readings - mean
    var = float(deviations @ deviations)
    rho = float(deviations[1:] @ deviations[:-1] / var) if var > 0 and n > 2 else 0.0
    rho = min(max(rho, 0.0), 0.99)
    n_eff = max(1.0, min(float(n), n * (1.0 - rho) / (1.0 + rho)))
    sd = float(np.std(readings, ddof=1))
    return MeanTypeA(mean, sd / float(np.sqrt(n_eff)), max(n_eff - 1.0, 1.0), n, n_eff, rho)


def bias_interval(bias: ArrayLike, u: ArrayLike, coverage: float = COVERAGE) -> NDArray[np.float64]:
    """Half-width U of the interval ±U about zero that holds `coverage` of an error N(bias, u²):
    Φ((U − b)/u) − Φ((−U − b)/u) = p, the quantile of a folded normal.

    For a result that keeps a known, uncorrected bias b beside a random part u (Phillips, Eberhardt
    and Parry, J. Res. NIST 102 (1997) 577: "uncertainty of measurement results containing
    uncorrected bias"). U is 1.96 u at b = 0 and tends to |b| + 1.645 u for |b| ≫ u; k·u with
    u = √(b² + u²) would cover an error near b every time, which is not a 95 % interval."""
    b = np.abs(np.asarray(bias, dtype=float))
    s = np.asarray(u, dtype=float)
    b, s = np.broadcast_arrays(b, s)
    lo = np.zeros(b.shape)
    hi = b + 10.0 * s + 1e-300
    for _ in range(80):  # bisection: the coverage is monotonic in U
        mid = 0.5 * (lo + hi)
        with np.errstate(divide="ignore", invalid="ignore"):
            held = special.ndtr((mid - b) / s) - special.ndtr((-mid - b) / s)
        held = np.where(s > 0, held, (mid >= b).astype(float))
        below = held < coverage
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return np.asarray(0.5 * (lo + hi), dtype=float)


def expanded_with_bias(
    bias: ArrayLike, u: ArrayLike, k_random: ArrayLike, coverage: float = COVERAGE
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(U, k) for a result with a known, uncorrected bias b beside a random part u whose own
    coverage factor is `k_random` (Student's t at its degrees of freedom): bias_interval with u
    widened by k_random/z, so that b = 0 gives k_random·u as before; k = U / √(b² + u²), the factor
    on the root-sum-square, which is what is reported as the standard uncertainty."""
    b = np.asarray(bias, dtype=float)
    random_part = np.asarray(u, dtype=float)
    k_random = np.asarray(k_random, dtype=float)
    expanded = bias_interval(
        b, random_part * k_random / special.ndtri(0.5 + coverage / 2.0), coverage
    )
    rss = np.hypot(b, random_part)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.where(rss > 0, expanded / np.where(rss > 0, rss, 1.0), k_random)
    return expanded, np.asarray(k, dtype=float)
