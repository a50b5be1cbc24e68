"""Electrolytic tilt sensor read through a 12-bit ADC (seed 003).

Designed for ±0.5 deg over 0-5 V: 3600 arcsec over 4096 counts, 0.88 arcsec per count
(seed 003 §2: 1.22 mV per count, 0.72 arcsec per mV). The bridge output follows tan(ε),
which is linear to far better than the ADC step over ±0.5 deg.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.physics.effects import EffectSet

ARCSEC_PER_RAD = 180.0 * 3600.0 / np.pi


@dataclass(frozen=True)
class AnalogSensor:
    """The ADC-read sensor's hardware; the one definition a scale scenario's `bench` is validated
    against."""

    adc_bits: int = field(default=12, metadata={"ge": 8, "le": 24})
    full_scale_v: float = field(default=5.0, metadata={"gt": 0, "le": 100})
    # ±0.5 deg over the full scale
    range_arcsec: float = field(default=3600.0, metadata={"gt": 0, "le": 36_000})
    # output at the sensor's own null (VCC/2)
    null_counts: float = field(default=2048.0, metadata={"ge": 0})
    temp_ref_c: float = field(default=20.0, metadata={"ge": -50, "le": 150})

    @property
    def counts(self) -> int:
        return int(2**self.adc_bits)

    @property
    def counts_per_arcsec(self) -> float:
        return self.counts / self.range_arcsec


def simulate_scale(
    sensor: AnalogSensor,
    fx: EffectSet,
    ref_arcsec: ArrayLike,
    start_arcsec: float,
    temp_c: ArrayLike | None = None,
    rng: np.random.Generator | None = None,
) -> dict[str, NDArray[np.float64]]:
    """ADC readings at reference angles (relative, zero at the first point) and the reference's
    readings.

    `start_arcsec` is the sensor's tilt from its own null at the reference's zero.
    """
    ref = np.atleast_1d(np.asarray(ref_arcsec, dtype=float))
    eps = ref + start_arcsec  # angle from the sensor's null
    k = sensor.counts_per_arcsec * (1.0 + fx.get("scale_factor", "k"))
    counts = sensor.null_counts + k * np.tan(eps / ARCSEC_PER_RAD) * ARCSEC_PER_RAD
    counts = (
        counts
        + fx.get("sensor_nonlinearity", "counts_per_arcsec2") * eps**2
        + fx.get("zero_offset", "counts")
    )
    if temp_c is not None:
        counts = counts + fx.get("temperature_drift", "counts_per_k") * (
            np.asarray(temp_c) - sensor.temp_ref_c
        )
    sigma = fx.get("noise", "reading_sigma_counts")
    if rng is not None and sigma > 0:
        counts = counts + rng.normal(0.0, sigma, counts.shape)
    reading = np.clip(np.floor(counts), 0, sensor.counts - 1)
    ref_sigma = fx.get("noise", "ref_sigma_arcsec")
    ref_read = ref + (
        rng.normal(0.0, ref_sigma, ref.shape) if rng is not None and ref_sigma > 0 else 0.0
    )
    return {"ref_arcsec": ref_read, "reading": reading, "true_ref_arcsec": ref}
