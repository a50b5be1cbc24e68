"""The discrepancy workflow on sensor-output-against-reference data (kind `scale`, seed 003).

Baseline `poly1`: the reference angle as a straight line in the sensor output, the lab's
"measurement equivalent" (arcsec per count) and zero. The candidate `sensor_nonlinearity`
raises the degree by one each time it is named (poly2, poly3, ...), so the question seed 003
asks of its Table 1, "is the output linear in the angle?", is the first step of the
workflow. `temperature_drift` (a zero coefficient) is a candidate when a temperature column
varies. Residuals are in arcsec.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.discrepancy import noise as noise_mod
from service.discrepancy import stats
from service.discrepancy.model import Block, Family, Fit
from service.discrepancy.report_types import (
    BaselineLine,
    DiscrepancyReport,
    MagnitudeEntry,
    ReportInputs,
)
from service.discrepancy.stage_data import TEMP_MIN_SPAN_K
from service.discrepancy.workflow import DEFAULT_ALPHA, Result, find_missing_effects, to_report
from service.errors import InputError

CANDIDATES = ("sensor_nonlinearity", "temperature_drift")
ALREADY_IN_MODEL = {
    "zero_offset": "the line's intercept",
    "scale_factor": "the line's slope (the measurement equivalent, arcsec per count)",
}
MAX_DEGREE = 6


class ScalePoly(Family):
    kind = "scale"
    baseline = "poly1"
    unit = "arcsec"
    axes = ("angle",)
    candidates = CANDIDATES
    already_in_model = ALREADY_IN_MODEL

    def __init__(
        self,
        reading: NDArray[np.float64],
        ref_arcsec: NDArray[np.float64],
        temp_c: NDArray[np.float64] | None,
        weight: float,
    ):
        super().__init__(ref_arcsec.reshape(-1, 1), np.array([weight]))
        self.reading = reading
        self.mid = 0.5 * (float(np.max(reading)) + float(np.min(reading)))
        self.half = max(0.5 * float(np.ptp(reading)), 1e-9)
        self.z = (reading - self.mid) / self.half
        self.dT = None if temp_c is None else temp_c - float(np.mean(temp_c))
        slope = (
            np.polyfit(self.z, ref_arcsec, 1)
            if np.ptp(reading) > 0
            else np.array([0.0, np.mean(ref_arcsec)])
        )
        self._init = (float(slope[1]), float(slope[0]))
        self._typ = max(float(np.ptp(ref_arcsec)), 1.0)

    def full_blocks(self, effects: tuple[str, ...]) -> list[Block]:
        out = [
            Block(
                "baseline", ("c0", "c1"), ("arcsec", "arcsec"), (self._typ, self._typ), self._init
            )
        ]
        deg = 1
        for effect in effects:
            if effect == "sensor_nonlinearity":
                deg += 1
                out.append(Block(effect, (f"c{deg}",), ("arcsec",), (0.01 * self._typ,), (0.0,)))
            elif effect == "temperature_drift":
                out.append(Block(effect, ("arcsec_per_k",), ("arcsec/K",), (1.0,), (0.0,)))
            else:
                raise KeyError(f"no scale term for {effect!r}")
        return out

    def predict_params(
        self, effects: tuple[str, ...], p: dict[str, dict[str, float]]
    ) -> NDArray[np.float64]:
        coeffs: dict[int, float] = {}
        for block in (p.get("baseline", {}), p.get("sensor_nonlinearity", {})):
            for lab, value in block.items():
                coeffs[int(lab[1:])] = value
        y = np.zeros_like(self.z)
        for j, coeff in coeffs.items():
            y = y + coeff * self.z**j
        if "temperature_drift" in effects and self.dT is not None:
            y = y + p["temperature_drift"].get("arcsec_per_k", 0.0) * self.dT
        return y.reshape(-1, 1)

    def magnitude(self, fit: Fit, effect: str) -> dict[str, MagnitudeEntry | int]:
        occ = sum(1 for block in fit.blocks if block.effect == effect) - 1
        sl = fit.block_slice(effect, occ)
        blk = fit.block(effect, occ)
        value = float(fit.values[sl][0])
        uncertainty = float(np.sqrt(max(fit.covariance[sl, sl][0, 0], 0.0)))
        if effect == "temperature_drift":
            return {
                "arcsec_per_k": {
                    "value": value,
                    "uncertainty": uncertainty,
                    "unit": "arcsec/K",
                    "what": "zero coefficient of the angle read from the output",
                }
            }
        j = int(blk.labels[0][1:])
        zj = self.z**j
        line = np.polyval(np.polyfit(self.z, zj, 1), self.z)
        dep = np.abs(zj - line)
        peak = float(np.max(dep))
        out: dict[str, MagnitudeEntry | int] = {
            f"c{j}_arcsec_per_count{j}": {
                "value": value / self.half**j,
                "uncertainty": uncertainty / self.half**j,
                "unit": f"arcsec/count^{j}",
                "what": f"coefficient of (output - {self.mid:g})^{j} in the angle",
            },
            "peak_departure_arcsec": {
                "value": abs(value) * peak,
                "uncertainty": uncertainty * peak,
                "unit": "arcsec",
                "what": "largest departure of this term from a straight line over the data",
            },
            "degree": j,
        }
        if j == 2:
            c1 = fit.values[fit.block_slice("baseline")][1] / self.half
            k = -value / self.half**2 / c1**3 if c1 else 0.0
            out["counts_per_arcsec2"] = {
                "value": float(k),
                "uncertainty": float(abs(k) * uncertainty / abs(value)) if value else 0.0,
                "unit": "count/arcsec^2",
                "what": "the same term in the registry's form, output += k·angle² "
                "(first-order inverse)",
            }
        return out

    def baseline_line(self, fit: Fit) -> BaselineLine:
        c0, c1 = fit.values[fit.block_slice("baseline")]
        std = np.sqrt(np.maximum(np.diag(fit.covariance[:2, :2]), 0.0))
        return {
            "arcsec_per_count": {
                "value": float(c1 / self.half),
                "uncertainty": float(std[1] / self.half),
                "unit": "arcsec/count",
                "what": "measurement equivalent (slope)",
            },
            "arcsec_at_zero_count": {
                "value": float(c0 - c1 * self.mid / self.half),
                "unit": "arcsec",
            },
        }


def scale_structure(
    reading: NDArray[np.float64],
    resid: NDArray[np.float64],
    temp_c: NDArray[np.float64] | None,
    t_s: NDArray[np.float64] | None,
    alpha: float = 0.01,
) -> list[stats.StructureTest]:
    resid_angle = resid[:, 0]
    tests: list[stats.StructureTest] = []
    z = (reading - reading.mean()) / max(float(np.ptp(reading)), 1e-9)
    if resid_angle.size >= 6:
        base = resid_angle - np.polyval(np.polyfit(z, resid_angle, 1), z)
        tests.append(
            stats.shape_test(
                base,
                ["output²", "output³"],
                np.column_stack([z**2, z**3]),
                "angle",
                "arcsec",
                {"output²": "bends one way over the range", "output³": "S-shaped"},
            )
        )
    if temp_c is not None and np.ptp(temp_c) >= TEMP_MIN_SPAN_K:
        test = stats.correlation_test(
            resid_angle, temp_c, "angle", "temp_c", "temperature", "K", "arcsec"
        )
        if test:
            tests.append(test)
    order = t_s if t_s is not None else np.arange(resid_angle.size, dtype=float)
    test = stats.runs_test(resid_angle, order, "angle")
    if test:
        tests.append(test)
    return stats.mark_significant(tests, alpha)


def _reference_arcsec(columns: Mapping[str, NDArray[np.float64]]) -> NDArray[np.float64]:
    """The reference angle in arcsec, whichever of the two units the data give it in."""
    if "ref_arcsec" in columns:
        return np.asarray(columns["ref_arcsec"], dtype=float)
    if "ref_deg" in columns:
        return np.asarray(columns["ref_deg"], dtype=float) * 3600.0
    raise InputError("missing required column 'ref_arcsec' or 'ref_deg' for kind 'scale'")


def _scale_noise(
    columns: Mapping[str, NDArray[np.float64]],
    reading: NDArray[np.float64],
    ref: NDArray[np.float64],
    noise_sigma: ArrayLike | None,
) -> noise_mod.NoiseLevel | None:
    """Repeated points first, then the stated noise level; None means 'from the final
    residual'."""
    noise = None
    if "point" in columns:
        # the scatter of repeated points, in the residual's terms: reference minus the line through
        # the outputs
        slope, icpt = np.polyfit(reading, ref, 1)
        scatter = ref - (slope * reading + icpt)
        noise = noise_mod.from_repeats(
            scatter.reshape(-1, 1), np.asarray(columns["point"]).reshape(-1, 1)
        )
    if noise is None and noise_sigma is not None:
        sigma = float(np.atleast_1d(noise_sigma)[0])
        if not sigma > 0:
            raise InputError(f"noise level must be positive, got {sigma}")
        noise = noise_mod.from_specification([sigma])
    return noise


def _scale_skips(temp: NDArray[np.float64] | None) -> dict[str, str]:
    """Candidates the data cannot support at all, with the reason in the lab's words."""
    skips = {}
    if temp is None:
        skips["temperature_drift"] = "no temp_c column"
    elif np.ptp(temp) < TEMP_MIN_SPAN_K:
        skips["temperature_drift"] = (
            f"temperature constant within {np.ptp(temp):.3g} K: a temperature coefficient "
            "cannot be told from the zero"
        )
    return skips


def analyse_scale(
    columns: Mapping[str, NDArray[np.float64]],
    noise_sigma: ArrayLike | None = None,
    alpha: float = DEFAULT_ALPHA,
) -> tuple[Result, ScalePoly]:
    ref = _reference_arcsec(columns)
    reading = np.asarray(columns["reading"], dtype=float)
    if np.unique(reading).size < 3:
        raise InputError(
            f"{np.unique(reading).size} distinct output values: a line and a test need at least 3"
        )
    temp = None if "temp_c" not in columns else np.asarray(columns["temp_c"], dtype=float)
    t_s = None if "t_s" not in columns else np.asarray(columns["t_s"], dtype=float)
    noise = _scale_noise(columns, reading, ref, noise_sigma)
    fam = ScalePoly(
        reading,
        ref,
        temp,
        1.0 if noise is None or noise.sigma is None else 1.0 / float(noise.sigma[0]),
    )
    fam.noise_known = noise is not None
    res = find_missing_effects(
        fam,
        CANDIDATES,
        _scale_skips(temp),
        noise or noise_mod.NoiseLevel(None, "final residual", np.inf, ""),
        lambda r: scale_structure(reading, r, temp, t_s),
        alpha=alpha,
        repeatable=("sensor_nonlinearity",),
        max_steps=MAX_DEGREE,
    )
    res.extra["baseline_fit"] = fam.baseline_line(res.fits[0])
    deg = 1 + sum(1 for step in res.steps if step.effect == "sensor_nonlinearity")
    res.extra["supported_degree"] = deg
    res.extra["supported_model"] = f"poly{deg}"
    return res, fam


def scale_report(
    columns: Mapping[str, NDArray[np.float64]],
    noise_sigma: ArrayLike | None = None,
    alpha: float = DEFAULT_ALPHA,
    inputs: ReportInputs | None = None,
) -> tuple[DiscrepancyReport, Result, ScalePoly]:
    res, fam = analyse_scale(columns, noise_sigma, alpha)
    rep = to_report(res, fam, {"n_rows": int(fam.reading.size), **(inputs or {})})
    return rep, res, fam
