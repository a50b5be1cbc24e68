"""Coverage of the offline methods' expanded uncertainties against the simulated truth.

For each method and scenario: calibrate on one simulated run, correct readings of another run
(fresh noise) and count how often |corrected - true| <= U, the expanded uncertainty `correct`
states for 95 %. Repeated over many noise realisations, the fraction is the coverage, with a
Wilson score interval (95 %) for a binomial proportion. A U that is honest gives about 0.95;
one computed from the wrong noise gives 0.99 (too wide) or 0.8 (too narrow).

The truth is the simulator's: the table tilt (stage), the rotation angle (rotation), the true
reference angle (scale), the true axis tilt (turntable), never a method's own formula.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.calibration.registry import FitExtras, FitOptions, get_method
from service.reproduce.stage_validation import Oracle, execute, paper_grid
from service.scenarios import load_scenario, parse_scenario, run_scenario

Z_95 = 1.959963984540054


def wilson(hits: int, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % for z = 1.96)."""
    if n == 0:
        return (0.0, 1.0)
    proportion = hits / n
    centre = (proportion + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(proportion * (1 - proportion) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return float(centre - half), float(centre + half)


@dataclass
class Row:
    """Coverage of one method on one scenario, for one axis (or one angle of a rotation sweep)."""

    kind: str
    method: str
    scenario: str
    axis: str
    hits: int
    n: int
    rms_error_over_u: float  # rms of (error / U): about 0.51 for an honest U at k ≈ 1.96

    @property
    def coverage(self) -> float:
        return self.hits / self.n if self.n else float("nan")

    @property
    def interval(self) -> tuple[float, float]:
        return wilson(self.hits, self.n)


class Tally:
    """Hits, points and the sum of (error / U)² per axis, added up over realisations."""

    def __init__(self) -> None:
        self.hits: dict[str, int] = {}
        self.n: dict[str, int] = {}
        self.z2: dict[str, float] = {}

    def add(self, axis: str, err: NDArray[np.float64], U: NDArray[np.float64]) -> None:
        ok = np.isfinite(err) & np.isfinite(U)
        error, expanded = err[ok], U[ok]
        self.hits[axis] = self.hits.get(axis, 0) + int(np.sum(np.abs(error) <= expanded))
        self.n[axis] = self.n.get(axis, 0) + int(error.size)
        self.z2[axis] = self.z2.get(axis, 0.0) + float(np.sum((error / expanded) ** 2))

    def rows(self, kind: str, method: str, scenario: str) -> list[Row]:
        return [
            Row(
                kind,
                method,
                scenario,
                axis,
                self.hits[axis],
                self.n[axis],
                float(np.sqrt(self.z2[axis] / self.n[axis])),
            )
            for axis in self.n
        ]


def _stage_scenario(readings_per_stand: int) -> Any:
    data = load_scenario("seed000").model_dump(mode="json", exclude_defaults=True)
    data["grid"]["readings_per_stand"] = readings_per_stand
    return parse_scenario(data)


# How the reference's noise is known to a stage fit: stated (the lab's certificate: the scenario's
# ref_sigma_deg, as `calibrate --ref-noise-deg` gives it), from 3 readings at each stand, or not at
# all (the conservative fallback).
STAGE_VARIANTS = ("ref noise stated", "3 readings per stand", "ref noise unknown")


def stage_coverage(
    method: str, variant: str, realisations: int, points: int = 81, seed0: int = 0
) -> list[Row]:
    """Stage method on the seed 000 bench: corrected measurement readings at `points` levelled
    targets vs the table tilt."""
    sc = _stage_scenario(3 if variant == "3 readings per stand" else 1)
    m = get_method("stage", method)
    tx, ty = paper_grid()
    pick = np.linspace(0, tx.size - 1, min(points, tx.size)).round().astype(int)
    tally = Tally()
    for k in range(realisations):
        seed = seed0 + k
        run = run_scenario(sc, seed=seed)
        assert run.effects is not None
        extra: FitExtras = (
            {"ref_noise_deg": run.effects.get("noise", "ref_sigma_deg")}
            if variant == "ref noise stated"
            else {}
        )
        model = m.fit(run.columns, FitOptions(extra=extra))
        oracle = Oracle(run.bench, run.effects, sc.environment.temp_c)
        cx, cy = oracle.level(tx[pick], ty[pick])
        val = execute(run.bench, run.effects, cx, cy, 700_000 + seed, sc.environment.temp_c)
        out = m.correct(model, {"meas_x_deg": val["meas_x_deg"], "meas_y_deg": val["meas_y_deg"]})
        for axis in ("x", "y"):
            tally.add(
                axis, out[f"tilt_{axis}_deg"] - val[f"tilt_{axis}_deg"], out[f"u_tilt_{axis}_deg"]
            )
    return tally.rows("stage", method, f"seed000, {variant}")


def rotation_coverage(method: str, preset: str, realisations: int, seed0: int = 0) -> list[Row]:
    """Rotation method: calibrate on one run of the sweep, correct another; one row per angle of the
    sweep."""
    sc = load_scenario(preset)
    m = get_method("rotation", method)
    tally = Tally()
    for k in range(realisations):
        cal = run_scenario(sc, seed=seed0 + 2 * k)
        val = run_scenario(sc, seed=seed0 + 2 * k + 1)
        model = m.fit(cal.columns, FitOptions())
        out = m.correct(model, val.columns)
        truth = val.truth["theta_true_deg"]
        err = (out["theta_deg"] - truth + 180.0) % 360.0 - 180.0
        for i, t in enumerate(truth):
            tally.add(f"theta {t:+.0f}", err[i : i + 1], out["u_theta_deg"][i : i + 1])
    return tally.rows("rotation", method, preset)


def scale_coverage(method: str, realisations: int, seed0: int = 0) -> list[Row]:
    """Scale method on the seed 003 bench: corrected readings of a fresh run vs the true reference
    angle."""
    sc = load_scenario("seed003")
    m = get_method("scale", method)
    tally = Tally()
    for k in range(realisations):
        model = m.fit(run_scenario(sc, seed=seed0 + 2 * k).columns, FitOptions())
        val = run_scenario(sc, seed=seed0 + 2 * k + 1)
        out = m.correct(model, val.columns)
        tally.add(
            "angle", out["angle_arcsec"] - val.truth["true_ref_arcsec"], out["u_angle_arcsec"]
        )
    return tally.rows("scale", method, "seed003")


def turntable_coverage(realisations: int, seed0: int = 0) -> list[Row]:
    """Reversal method on the seed 004 turntable: corrected pairs of a fresh run vs the true axis
    tilt."""
    sc = load_scenario("seed004")
    m = get_method("turntable", "reversal")
    tally = Tally()
    for k in range(realisations):
        model = m.fit(run_scenario(sc, seed=seed0 + 2 * k).columns, FitOptions())
        val = run_scenario(sc, seed=seed0 + 2 * k + 1)
        out = m.correct(model, val.columns)
        tally.add(
            "north", out["north_arcsec"] - val.truth["true_north_arcsec"], out["u_north_arcsec"]
        )
        tally.add("east", out["east_arcsec"] - val.truth["true_east_arcsec"], out["u_east_arcsec"])
    return tally.rows("turntable", "reversal", "seed004")


def offline_cases(realisations: int) -> Iterator[tuple[str, Callable[[], list[Row]]]]:
    """Every offline (method, scenario) case of the table, lazily (each takes seconds to
    minutes)."""
    for method in ("homography", "axis-transform", "kinematic"):
        for variant in STAGE_VARIANTS:
            yield (
                f"stage {method} ({variant})",
                partial(stage_coverage, method, variant, realisations),
            )
    # the coupling method corrects nothing of the measurement sensor: its U is the size of the
    # installation error it leaves, the same whatever is known of the reference's noise
    yield (
        "stage coupling (ref noise stated)",
        partial(stage_coverage, "coupling", "ref noise stated", realisations),
    )
    for preset in ("seed002-b55", "seed002-b75", "seed002-sim"):
        for method in ("iodsra", "iodsra-combined"):
            yield (
                f"rotation {method} {preset}",
                partial(rotation_coverage, method, preset, realisations),
            )
    yield (
        "rotation direct seed002-sim",
        lambda: rotation_coverage("direct", "seed002-sim", realisations),
    )
    yield "scale poly1 seed003", lambda: scale_coverage("poly1", realisations)
    yield "turntable reversal seed004", lambda: turntable_coverage(realisations)


def daemon_rows(
    calibrations: int,
    scenarios: tuple[str, ...] = ("seed000", "rough"),
    each: Callable[[str, int, Any], None] | None = None,
) -> list[Row]:
    """The daemon path (GET /tilt against the simulated world's true tilt,
    service/reproduce/daemon_coverage.py): per scenario and axis, one reading's U over every
    distinct reading and the averaged tilt's U over every stand, pooled over `calibrations`
    calibrations (each a fresh daemon: minutes each). `each(scenario, k, readings)` is told every
    calibration's StandReadings as they come (a benchmark prints each one's figures)."""
    # an in-process daemon: imported only when asked for
    from service.reproduce.daemon_coverage import measure

    rows = []
    for scenario in scenarios:
        single, averaged = Tally(), Tally()
        for k, got in enumerate(measure(scenario, calibrations)):
            if each is not None:
                each(scenario, k, got)
            for i, axis in enumerate("xy"):
                single.add(axis, got.errors[:, i], got.expanded[:, i])
                averaged.add(axis, got.mean_errors[:, i], got.mean_expanded[:, i])
        rows += single.rows(
            "daemon", "GET /tilt (one reading)", f"{scenario}, {calibrations} calibrations"
        )
        rows += averaged.rows(
            "daemon",
            "GET /tilt?average_s (mean at rest)",
            f"{scenario}, {calibrations} calibrations",
        )
    return rows
