"""Bench time a job spends, by activity: what a lab sells.

Counted on the bench clock (a simulated bench's speed-up runs it faster, so the counts do not change
with the speed): moving (both stage moves of a point, approach and final), settling (from the stage
standing to the readings being settled) and reading (from settled to the point's last reading).
`total` is their sum; the daemon's own computing between points (storing, fitting) is not bench time
and is not counted.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass


@dataclass
class BenchTime:
    moving: float = 0.0
    settling: float = 0.0
    reading: float = 0.0

    @property
    def total(self) -> float:
        return self.moving + self.settling + self.reading

    def add(self, *, moving: float = 0.0, settling: float = 0.0, reading: float = 0.0) -> None:
        self.moving += max(moving, 0.0)
        self.settling += max(settling, 0.0)
        self.reading += max(reading, 0.0)

    def as_json(self) -> dict[str, float]:
        """The job's and the record's `bench_seconds`."""
        return {
            "total": round(self.total, 3),
            "moving": round(self.moving, 3),
            "settling": round(self.settling, 3),
            "reading": round(self.reading, 3),
        }

    @classmethod
    def from_json(cls, stored: Mapping[str, float] | None) -> BenchTime:
        """What a job had counted before (a resumed job goes on counting from there)."""
        if not stored:
            return cls()
        return cls(
            float(stored.get("moving", 0.0)),
            float(stored.get("settling", 0.0)),
            float(stored.get("reading", 0.0)),
        )
