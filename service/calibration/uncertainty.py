"""GUM law of propagation of uncertainty (JCGM 100 §5) for corrected values.

The measurand y = f(p, x) depends on fitted parameters p (covariance from the fit) and
the readings x (independent white noise). Sensitivities are central differences, vectorised
over points; expanded uncertainty U = k · u_c with k = 2.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

K_EXPANDED = 2.0


def _step(value, variance, rel_step: float):
    """Finite-difference step: small against the value and against its own uncertainty.

    Relative to the value, so parameters in any unit (counts per arcsec, rad, deg) are stepped
    alike; at least a thousandth of the standard uncertainty, so a value near zero is not
    stepped by less than its own noise can resolve; rel_step where both are zero.
    """
    h = np.maximum(rel_step * np.abs(value), 1e-3 * np.sqrt(max(float(variance), 0.0)))
    return np.where(h > 0, h, rel_step)


def propagate(
    f: Callable[[np.ndarray, Mapping[str, np.ndarray]], np.ndarray],
    params: np.ndarray,
    cov: np.ndarray | None,
    inputs: Mapping[str, np.ndarray],
    input_sigma: Mapping[str, float] | None = None,
    rel_step: float = 1e-6,
) -> np.ndarray:
    """Standard uncertainty of each output of f.

    `f(p, inputs)` returns an array (N,) or (N, m). Returns the same shape: combined standard
    uncertainty u_c from the parameter covariance and the input noise (no correlation between
    the two, which holds when the readings being corrected are not the calibration data).
    """
    params = np.asarray(params, dtype=float)
    y0 = np.asarray(f(params, inputs), dtype=float)
    var = np.zeros_like(y0)
    if cov is not None and params.size:
        jac = []
        for i in range(params.size):
            h = _step(params[i], cov[i][i], rel_step)
            pp, pm = params.copy(), params.copy()
            pp[i] += h
            pm[i] -= h
            jac.append((np.asarray(f(pp, inputs)) - np.asarray(f(pm, inputs))) / (2 * h))
        J = np.stack(jac, axis=-1)  # (..., n_params)
        var = var + np.einsum("...i,ij,...j->...", J, np.asarray(cov), J)
    for name, sigma in (input_sigma or {}).items():
        if not sigma:
            continue
        x = np.asarray(inputs[name], dtype=float)
        h = _step(x, sigma ** 2, rel_step)
        up = dict(inputs)
        dn = dict(inputs)
        up[name] = x + h
        dn[name] = x - h
        d = (np.asarray(f(params, up)) - np.asarray(f(params, dn))) / (2 * h if y0.ndim == 1 else (2 * h)[:, None])
        var = var + (d * sigma) ** 2
    return np.sqrt(var)


def expanded(u: np.ndarray, k: float = K_EXPANDED) -> np.ndarray:
    return k * np.asarray(u)
