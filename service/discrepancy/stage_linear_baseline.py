"""The `linear` baseline of a stage bench: a projective map from stage angles to sensor angles.

This is seed 000's H1 without its eq. (10), written in the forward direction (stage → sensor)
because the workflow compares predicted with measured readings. Every candidate acts where
its effect acts on the bench:

* actuator effects change the stage angle before the map: backlash (−dir·width/2, as the
  simulator and the worm gear do), periodic error (a sine of the worm phase);
* off-axis coupling changes the geometry before the map: the upper stage's angle becomes
  asin(sin θx · cos θy) about the bench's level point (κ = 1 is the stacked geometry);
* sensor effects change the reading after the map: quadratic nonlinearity, temperature
  coefficients of zero and scale, and a linear zero drift in time.

Effects a projective map already represents to first order (zero offsets, scale factors,
sensor yaw and non-orthogonality, mounting tilts, stage-axis misalignment, stage scale) are
"already in the model"; `ALREADY_IN_MODEL` says why for each.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from service.calibration.projective import fit_projective
from service.discrepancy.model import Block, Family, Fit
from service.discrepancy.report_types import MagnitudeEntry
from service.discrepancy.stage_data import (
    STAGE_CANDIDATES,
    STAGE_SEPARABILITY_HINTS,
    StageData,
    candidate_block,
    sensor_param_names,
)
from service.physics.stage import offaxis_error_deg

ALREADY_IN_MODEL = {
    "zero_offset": "the map's translation terms (h13, h23) are the sensor's zero offsets",
    "scale_factor": "the map's diagonal terms are the sensor's gains",
    "sensor_yaw": "a yawed sensor mixes the two table tilts linearly: the map's off-diagonal terms",
    "non_orthogonality": "an axis turned from 90° mixes the tilts linearly: an off-diagonal term "
    "of the map",
    "mounting_tilt": "tilted mounting planes shift the readings (translation terms) and, to "
    "first order, mix them linearly; the off-axis candidate's level point carries the rest",
    "axis_misalignment": "misaligned stage axes mix and shear the stage angles: linear to first "
    "order, the projective terms carry the leading perspective part",
    "stage_scale": "a gear-ratio error scales a stage angle: the map's diagonal terms (to first "
    "order; it acts before the off-axis coupling, a second-order difference)",
}


class OnStageData(Protocol):
    """A family fitted to stage data: what the magnitudes of its effects are stated against."""

    data: StageData


class StageLinear(Family):
    kind = "stage"
    baseline = "linear"
    unit = "deg"
    axes = ("x", "y")

    def __init__(self, data: StageData, weights: NDArray[np.float64]):
        super().__init__(data.observed, weights)
        self.data = data
        self.qx, self.qy = data.quantised()
        self.s = max(float(np.max(np.abs(np.concatenate([self.qx, self.qy])))), 1.0)
        self.dT = None if data.temp_c is None else data.temp_c - float(np.mean(data.temp_c))
        self.t_h = None if data.t_s is None else (data.t_s - float(np.mean(data.t_s))) / 3600.0
        self.wx = 2.0 * np.pi * self.qx / data.bench.worm_period_x_deg
        self.wy = 2.0 * np.pi * self.qy / data.bench.worm_period_y_deg
        self.names = sensor_param_names(data.sensor)

    candidates = STAGE_CANDIDATES
    already_in_model = ALREADY_IN_MODEL
    separability_hints = {
        **STAGE_SEPARABILITY_HINTS,
        "sensor_nonlinearity": "the map's perspective terms and the coupling's level point take "
        "most of a quadratic up; the kinematic baseline (--baseline kinematic) has no "
        "perspective terms and separates it",
    }

    def full_blocks(self, effects: tuple[str, ...]) -> list[Block]:
        out = [
            Block(
                "baseline",
                tuple(f"h{i}" for i in ("11", "12", "13", "21", "22", "23", "31", "32")),
                ("1",) * 8,
                (1.0, 0.1, 0.1, 0.1, 1.0, 0.1, 0.01, 0.01),
                (1, 0, 0, 0, 1, 0, 0, 0),
            )
        ]
        for effect in effects:
            if effect == "offaxis_coupling":
                out.append(
                    Block(
                        effect,
                        ("kappa", "level_x_deg", "level_y_deg"),
                        ("1", "deg", "deg"),
                        (1.0, 0.1, 0.1),
                        (1.0, 0.0, 0.0),
                    )
                )
            elif (block := candidate_block(effect, self.names)) is not None:
                out.append(block)
            else:
                raise KeyError(f"the linear baseline has no term for {effect!r}")
        return out

    # -- the model ---------------------------------------------------------------------------------
    def stage_angles(
        self, effects: tuple[str, ...], p: dict[str, dict[str, float]]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Angles the stages reach (deg): actuator effects before the geometry and the map."""
        tx, ty = self.qx.copy(), self.qy.copy()
        data = self.data
        if "backlash" in effects:
            backlash = p["backlash"]
            if data.dir_x is not None:
                tx = tx - data.dir_x * backlash.get("x_deg", 0.0) / 2.0
            if data.dir_y is not None:
                ty = ty - data.dir_y * backlash.get("y_deg", 0.0) / 2.0
        if "periodic_error" in effects:
            periodic = p["periodic_error"]
            tx = (
                tx
                + periodic.get("x_sin_deg", 0.0) * np.sin(self.wx)
                + periodic.get("x_cos_deg", 0.0) * np.cos(self.wx)
            )
            ty = (
                ty
                + periodic.get("y_sin_deg", 0.0) * np.sin(self.wy)
                + periodic.get("y_cos_deg", 0.0) * np.cos(self.wy)
            )
        return tx, ty

    def map_inputs(
        self,
        effects: tuple[str, ...],
        p: dict[str, dict[str, float]],
        tx: NDArray[np.float64],
        ty: NDArray[np.float64],
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Stage angles as the map sees them: through the stacked geometry when coupling is
        modelled."""
        if "offaxis_coupling" not in effects:
            return tx, ty
        coupling = p["offaxis_coupling"]
        xa = tx + coupling.get("level_x_deg", 0.0)
        yb = ty + coupling.get("level_y_deg", 0.0)
        return xa - coupling.get("kappa", 1.0) * offaxis_error_deg(xa, yb), yb

    def predict_params(
        self, effects: tuple[str, ...], p: dict[str, dict[str, float]]
    ) -> NDArray[np.float64]:
        tx, ty = self.stage_angles(effects, p)
        map_x, map_y = self.map_inputs(effects, p, tx, ty)
        homography = p["baseline"]
        un, vn = map_x / self.s, map_y / self.s
        denom = homography["h31"] * un + homography["h32"] * vn + 1.0
        denom = np.where(np.abs(denom) < 1e-9, 1e-9, denom)
        X0 = self.s * (homography["h11"] * un + homography["h12"] * vn + homography["h13"]) / denom
        Y0 = self.s * (homography["h21"] * un + homography["h22"] * vn + homography["h23"]) / denom
        pred_x, pred_y = X0.copy(), Y0.copy()
        if "sensor_nonlinearity" in effects:
            coeffs = p["sensor_nonlinearity"]
            nx, ny = self.names["sensor_nonlinearity"]
            pred_x += coeffs.get(nx, 0.0) * X0**2
            pred_y += coeffs.get(ny, 0.0) * Y0**2
        if "temperature_drift" in effects and self.dT is not None:
            coeffs = p["temperature_drift"]
            zx, zy, sc = self.names["temperature_drift"]
            pred_x += coeffs.get(zx, 0.0) * self.dT + coeffs.get(sc, 0.0) * X0 * self.dT
            pred_y += coeffs.get(zy, 0.0) * self.dT + coeffs.get(sc, 0.0) * Y0 * self.dT
        if "time_drift" in effects and self.t_h is not None:
            coeffs = p["time_drift"]
            rx, ry = self.names["time_drift"]
            pred_x += coeffs.get(rx, 0.0) * self.t_h
            pred_y += coeffs.get(ry, 0.0) * self.t_h
        return np.column_stack([pred_x, pred_y])

    def initial(
        self, effects: tuple[str, ...], blocks: list[Block], start: Fit | None
    ) -> NDArray[np.float64]:
        """Previous values where they carry over; the map re-estimated by DLT when the geometry
        changed."""
        x = super().initial(effects, blocks, start)
        changed = start is None or ("offaxis_coupling" in effects) != (
            "offaxis_coupling" in start.effects
        )
        if changed:
            params = self.unpack(blocks, x)
            tx, ty = self.stage_angles(effects, params)
            map_x, map_y = self.map_inputs(effects, params, tx, ty)
            homography = fit_projective(
                map_x / self.s,
                map_y / self.s,
                self.observed[:, 0] / self.s,
                self.observed[:, 1] / self.s,
                refine=False,
                what=f"{self.data.sensor} readings against stage angles",
            )
            x[:8] = homography.ravel()[:8]
        return x

    # -- reporting
    # -----------------------------------------------------------------------------------
    def magnitude(self, fit: Fit, effect: str) -> dict[str, MagnitudeEntry]:
        return stage_magnitude(self, fit, effect)


def _entry(value: float, std: float, unit: str, doc: str | None = None) -> MagnitudeEntry:
    entry: MagnitudeEntry = {"value": float(value), "uncertainty": float(std), "unit": unit}
    if doc:
        entry["what"] = doc
    return entry


def stage_magnitude(fam: OnStageData, fit: Fit, effect: str) -> dict[str, MagnitudeEntry]:
    """Fitted parameters of one effect, in the registry's names and units where it has them."""
    sl = fit.block_slice(effect)
    blk = fit.block(effect)
    vals = fit.values[sl]
    cov = fit.covariance[sl, sl]
    if effect == "periodic_error":
        return _periodic_magnitude(fam, blk, vals, cov)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    out: dict[str, MagnitudeEntry] = {}
    for lab, unit, value, sigma in zip(blk.labels, blk.units, vals, std):
        out[lab] = _entry(value, sigma, unit)
    if effect == "offaxis_coupling" and "kappa" in out:
        _add_offaxis_peak(fam, out)
    return out


def _periodic_magnitude(
    fam: OnStageData, blk: Block, vals: NDArray[np.float64], cov: NDArray[np.float64]
) -> dict[str, MagnitudeEntry]:
    """The worm's periodic error as the registry states it (amplitude and phase per stage), not as
    the sine and cosine terms it is fitted by."""
    out: dict[str, MagnitudeEntry] = {}
    for ax in ("x", "y"):
        ls, lc = f"{ax}_sin_deg", f"{ax}_cos_deg"
        if ls not in blk.labels or lc not in blk.labels:
            # one of the pair held (the points sample too few phases of the worm): no amplitude
            continue
        i, j = blk.labels.index(ls), blk.labels.index(lc)
        amp, u_amp, phase_deg, u_ph = _amplitude_phase(
            vals[i], vals[j], cov[np.ix_([i, j], [i, j])]
        )
        period = fam.data.bench.worm_period_x_deg if ax == "x" else fam.data.bench.worm_period_y_deg
        out[f"{ax}_amp_deg"] = _entry(
            amp, u_amp, "deg", f"amplitude at the worm period {period:g} deg"
        )
        out[f"{ax}_phase_deg"] = _entry(phase_deg, u_ph, "deg")
    return out


def _amplitude_phase(
    sin_coef: float, cos_coef: float, c2: NDArray[np.float64]
) -> tuple[float, float, float, float]:
    """Amplitude and phase (deg) of a sine-cosine pair with their uncertainties, propagated from
    the pair's covariance `c2` through the gradients (phase uncertainty 180 deg at zero
    amplitude)."""
    amp = float(np.hypot(sin_coef, cos_coef))
    grad_amp = np.array([sin_coef, cos_coef]) / amp if amp > 0 else np.array([1.0, 0.0])
    u_amp = float(np.sqrt(max(float(grad_amp @ c2 @ grad_amp), 0.0)))
    grad_phase = np.array([-cos_coef, sin_coef]) / amp**2 if amp > 0 else np.zeros(2)
    u_ph = (
        float(np.degrees(np.sqrt(max(float(grad_phase @ c2 @ grad_phase), 0.0))))
        if amp > 0
        else 180.0
    )
    return amp, u_amp, float(np.degrees(np.arctan2(cos_coef, sin_coef))), u_ph


def _add_offaxis_peak(fam: OnStageData, out: dict[str, MagnitudeEntry]) -> None:
    """Say what κ means and what it amounts to: the largest off-axis error over the grid."""
    out["kappa"]["what"] = "1 = the stacked-stage geometry of seed 000 eq. (9)"
    x, y = fam.data.cmd_x_deg, fam.data.cmd_y_deg
    err = -offaxis_error_deg(x, y) * out["kappa"]["value"]
    out["peak_offaxis_error_deg"] = _entry(
        float(np.max(np.abs(err))),
        float(
            np.max(np.abs(err))
            * out["kappa"]["uncertainty"]
            / max(abs(out["kappa"]["value"]), 1e-12)
        ),
        "deg",
        "largest off-axis error of the x reading over the grid (seed 000 eq. 10)",
    )
