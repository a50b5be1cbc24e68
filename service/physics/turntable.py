"""Biaxial inclinometer on a turntable read in symmetric positions (seed 004, docs/models.md §4)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.physics.effects import EffectSet


@dataclass(frozen=True)
class TurntableInclinometer:
    """Parameters that calibration estimates (β, ε in degrees; m in reading units per arcsec).

    The one definition a turntable scenario's `bench` is validated against (`default`: the
    scenario's default where the physics has none).
    """

    beta_deg: float = field(metadata={"ge": -180, "le": 180})
    epsilon_deg: float = field(metadata={"ge": -5, "le": 5, "default": 0.0})
    m1: float = field(metadata={"gt": 0, "le": 1000})
    m2: float = field(metadata={"gt": 0, "le": 1000})


def turntable_readings(
    p: TurntableInclinometer,
    azimuth_deg: ArrayLike,
    north_arcsec: ArrayLike,
    east_arcsec: ArrayLike,
    z1: float = 0.0,
    z2: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """n1(A), n2(A) of docs/models.md §4 for axis tilt (ξ north, η east) in arcsec."""
    angle_rad = np.radians(np.asarray(azimuth_deg, dtype=float) + p.beta_deg)
    epsilon_rad = np.radians(p.epsilon_deg)
    xi, eta = np.asarray(north_arcsec, dtype=float), np.asarray(east_arcsec, dtype=float)
    n1 = p.m1 * (xi * np.cos(angle_rad) + eta * np.sin(angle_rad)) + z1
    n2 = p.m2 * (-xi * np.sin(angle_rad + epsilon_rad) + eta * np.cos(angle_rad + epsilon_rad)) + z2
    return n1, n2


def simulate_turntable(
    p: TurntableInclinometer,
    fx: EffectSet,
    azimuth_deg: ArrayLike,
    north_arcsec: ArrayLike,
    east_arcsec: ArrayLike,
    rotation_deg: float = 180.0,
    pair_interval_s: float = 120.0,
    rng: np.random.Generator | None = None,
) -> dict[str, NDArray[np.float64]]:
    """One row per symmetric pair: readings at A and at A + φ (the true φ, which may differ from
    180)."""
    az = np.atleast_1d(np.asarray(azimuth_deg, dtype=float))
    xi = np.broadcast_to(np.asarray(north_arcsec, dtype=float), az.shape)
    eta = np.broadcast_to(np.asarray(east_arcsec, dtype=float), az.shape)
    z1, z2 = fx.get("zero_offset", "z1"), fx.get("zero_offset", "z2")
    drift = fx.get("time_drift", "reading_per_h") * pair_interval_s / 3600.0
    sigma, res = fx.get("noise", "reading_sigma"), fx.get("noise", "resolution")
    out: dict[str, NDArray[np.float64]] = {"azimuth_deg": az}
    for tag, azimuth, dz in (("a", az, 0.0), ("b", az + rotation_deg, drift)):
        n1, n2 = turntable_readings(p, azimuth, xi, eta, z1 + dz, z2 + dz)
        for name, n in (("n1", n1), ("n2", n2)):
            if rng is not None and sigma > 0:
                n = n + rng.normal(0.0, sigma, n.shape)
            if res > 0:
                n = np.round(n / res) * res
            out[f"{name}_{tag}"] = n
    ref_sigma = fx.get("noise", "ref_sigma_arcsec")
    for col, ref_true_arcsec in (("ref_north_arcsec", xi), ("ref_east_arcsec", eta)):
        out[col] = ref_true_arcsec + (
            rng.normal(0.0, ref_sigma, ref_true_arcsec.shape)
            if rng is not None and ref_sigma > 0
            else 0.0
        )
    out["true_north_arcsec"], out["true_east_arcsec"] = xi.copy(), eta.copy()
    return out
