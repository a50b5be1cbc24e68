"""Triaxial inclinometer rotating about an axis inclined β to the horizontal (seed 002,
docs/models.md §3).

The outputs are the sines S of the axes' angles to the horizontal with seed 002's signs;
docs/models.md §3's three output equations are the contract and are written here as they stand.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.physics.effects import EffectSet


@dataclass(frozen=True)
class RotationBench:
    """Orientation of the triaxial module on the inclined rotation axis; the one definition a
    rotation scenario's `bench` is validated against."""

    alpha_deg: float = field(metadata={"ge": -180, "le": 180})
    beta_deg: float = field(metadata={"ge": -89, "le": 89})
    gamma_deg: float = field(metadata={"ge": -45, "le": 45})


def rotation_outputs(
    alpha_deg: ArrayLike, beta_deg: ArrayLike, gamma_deg: ArrayLike, theta_deg: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Ideal (Sx, Sy, Sz) at rotation angle θ."""
    alpha, beta, gamma, theta = (
        np.radians(np.asarray(angle_deg, dtype=float))
        for angle_deg in (alpha_deg, beta_deg, gamma_deg, theta_deg)
    )
    in_plane = np.cos(gamma) * np.sin(beta) + np.sin(gamma) * np.cos(beta) * np.cos(theta)
    across = np.cos(beta) * np.sin(theta)
    sx = -across * np.cos(alpha) + in_plane * np.sin(alpha)
    sy = across * np.sin(alpha) + in_plane * np.cos(alpha)
    sz = -np.sin(gamma) * np.sin(beta) + np.cos(gamma) * np.cos(beta) * np.cos(theta)
    return sx, sy, sz


def simulate_rotation(
    bench: RotationBench,
    fx: EffectSet,
    theta_deg: ArrayLike,
    rng: np.random.Generator | None = None,
) -> dict[str, NDArray[np.float64]]:
    """Sensor outputs at the reference angles, with the sine-domain errors of the effect set.

    Returns `sx`, `sy`, `sz`, `theta_ref_deg` (the dividing head's reading, with its own
    noise) and `theta_true_deg`.
    """
    theta = np.atleast_1d(np.asarray(theta_deg, dtype=float))
    ideal = dict(
        zip(
            ("sx", "sy", "sz"),
            rotation_outputs(bench.alpha_deg, bench.beta_deg, bench.gamma_deg, theta),
        )
    )
    sigma = fx.get("noise", "sigma_s")
    out: dict[str, NDArray[np.float64]] = {}
    for ax, ideal_sine in ideal.items():
        output = (
            ideal_sine * (1.0 + fx.get("scale_factor", ax))
            + fx.get("sensor_nonlinearity", ax) * ideal_sine**2
            + fx.get("zero_offset", ax)
        )
        if rng is not None and sigma > 0:
            output = output + rng.normal(0.0, sigma, output.shape)
        out[ax] = output
    ref_sigma = fx.get("noise", "theta_ref_sigma_deg")
    out["theta_ref_deg"] = theta + (
        rng.normal(0.0, ref_sigma, theta.shape) if rng is not None and ref_sigma > 0 else 0.0
    )
    out["theta_true_deg"] = theta
    return out
