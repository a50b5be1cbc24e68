"""When readings after a move have settled, by a statistical test rather than a fixed window.

After n readings since the move, the last 3k of them (k = max(`block`, n // 12): blocks grow with
the time waited, so a slow sensor's drift is seen over a span comparable to its time constant) are
cut into three blocks of k. The sensor has settled when the mean of the newest block differs from
the means of each of the two before it by less than `z` standard errors of a block mean, σ/√k, on
every channel, σ being the reading noise (known from an earlier point at rest). While a transient
decays, the block means walk away from each other and the test fails; once what is left of it is
within the noise, it passes. On a bench without settling it passes after three blocks of `block`.
A small transient of a slow sensor (a short move) would pass on short blocks that cannot see it: a
job raises `block` to half the block its longest transient so far passed with (the sensor's
slowness, learnt where it showed).
The rule is pure (arrays in, a count out) so it is tested on recorded steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

BLOCK = 4  # readings per block
Z = 2.0  # block means closer than Z standard errors of a block mean are the same
SETTLING_RULE = (
    f"statistical: after n readings, the mean of the newest k = max({BLOCK}, n/12) readings "
    f"within {Z:g} standard errors (reading noise / sqrt(k)) of each of the two blocks of k "
    "before it, on every channel"
)


@dataclass(frozen=True)
class SettleTest:
    noise_deg: float  # σ of one reading (per channel), from the bench at rest
    block: int = BLOCK
    z: float = Z

    def threshold(self, k: int) -> float:
        return self.z * self.noise_deg / float(np.sqrt(k))

    def block_at(self, n: int) -> int:
        """The block (readings) the test uses after `n` readings: `block`, or n / 12 once longer."""
        return max(self.block, n // 12)

    def settled_after(self, values: ArrayLike, checked: int = 0) -> int | None:
        """The number of readings (from the first after the move) after which the test first passes,
        or None. `values` is (n,) or (n, channels); counts up to `checked` are known not to pass (an
        earlier call)."""
        samples = np.asarray(values, dtype=float)
        if samples.ndim == 1:
            samples = samples[:, None]
        for end in range(max(3 * self.block, checked + 1), samples.shape[0] + 1):
            k = self.block_at(end)
            m3 = samples[end - k : end].mean(axis=0)
            m2 = samples[end - 2 * k : end - k].mean(axis=0)
            m1 = samples[end - 3 * k : end - 2 * k].mean(axis=0)
            if np.abs(m3 - m2).max() < self.threshold(k) and np.abs(m3 - m1).max() < self.threshold(
                k
            ):
                return end
        return None


@dataclass
class StandSettling:
    """When the readings at the stage's present stand passed the settling test: the start of what an
    averaged tilt may take (a window reaching back to the move's end would hold the table's
    transient, and the U of its mean would be that of the transient). Kept per stand and advanced as
    readings arrive, so each request tests only the readings it has not seen."""

    stand_bench_s: float | None = None  # the stand's mark (the stage stood still from then)
    checked: int = 0  # readings since the mark known not to pass
    settled_bench_s: float | None = None

    def settled_since(
        self, stand_bench_s: float, values: ArrayLike, stamps: ArrayLike, noise_deg: float
    ) -> float | None:
        """The bench time of the reading at which the readings since `stand_bench_s` (`values`, (n,
        channels), stamped `stamps`, oldest first) first passed the test against `noise_deg`; None
        while they have not."""
        if stand_bench_s != self.stand_bench_s:
            self.stand_bench_s, self.checked, self.settled_bench_s = stand_bench_s, 0, None
        if self.settled_bench_s is None:
            samples = np.asarray(values, dtype=float)
            n = SettleTest(noise_deg).settled_after(samples, self.checked)
            self.checked = int(samples.shape[0])
            if n is not None:
                self.settled_bench_s = float(np.asarray(stamps, dtype=float)[n - 1])
        return self.settled_bench_s
