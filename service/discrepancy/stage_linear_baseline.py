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

from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from service.calibration.projective import fit_projective
from service.discrepancy.model import Block, Family, Fit
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
        for e in effects:
            if e == "offaxis_coupling":
                out.append(
                    Block(
                        e,
                        ("kappa", "level_x_deg", "level_y_deg"),
                        ("1", "deg", "deg"),
                        (1.0, 0.1, 0.1),
                        (1.0, 0.0, 0.0),
                    )
                )
            elif (block := candidate_block(e, self.names)) is not None:
                out.append(block)
            else:
                raise KeyError(f"the linear baseline has no term for {e!r}")
        return out

    # -- the model ---------------------------------------------------------------------------------
    def stage_angles(
        self, effects: tuple[str, ...], p: dict[str, dict[str, float]]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Angles the stages reach (deg): actuator effects before the geometry and the map."""
        tx, ty = self.qx.copy(), self.qy.copy()
        d = self.data
        if "backlash" in effects:
            b = p["backlash"]
            if d.dir_x is not None:
                tx = tx - d.dir_x * b.get("x_deg", 0.0) / 2.0
            if d.dir_y is not None:
                ty = ty - d.dir_y * b.get("y_deg", 0.0) / 2.0
        if "periodic_error" in effects:
            q = p["periodic_error"]
            tx = (
                tx
                + q.get("x_sin_deg", 0.0) * np.sin(self.wx)
                + q.get("x_cos_deg", 0.0) * np.cos(self.wx)
            )
            ty = (
                ty
                + q.get("y_sin_deg", 0.0) * np.sin(self.wy)
                + q.get("y_cos_deg", 0.0) * np.cos(self.wy)
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
        c = p["offaxis_coupling"]
        xa = tx + c.get("level_x_deg", 0.0)
        yb = ty + c.get("level_y_deg", 0.0)
        return xa - c.get("kappa", 1.0) * offaxis_error_deg(xa, yb), yb

    def predict_params(
        self, effects: tuple[str, ...], p: dict[str, dict[str, float]]
    ) -> NDArray[np.float64]:
        tx, ty = self.stage_angles(effects, p)
        u, v = self.map_inputs(effects, p, tx, ty)
        h = p["baseline"]
        un, vn = u / self.s, v / self.s
        w = h["h31"] * un + h["h32"] * vn + 1.0
        w = np.where(np.abs(w) < 1e-9, 1e-9, w)
        X0 = self.s * (h["h11"] * un + h["h12"] * vn + h["h13"]) / w
        Y0 = self.s * (h["h21"] * un + h["h22"] * vn + h["h23"]) / w
        X, Y = X0.copy(), Y0.copy()
        if "sensor_nonlinearity" in effects:
            q = p["sensor_nonlinearity"]
            nx, ny = self.names["sensor_nonlinearity"]
            X += q.get(nx, 0.0) * X0**2
            Y += q.get(ny, 0.0) * Y0**2
        if "temperature_drift" in effects and self.dT is not None:
            q = p["temperature_drift"]
            zx, zy, sc = self.names["temperature_drift"]
            X += q.get(zx, 0.0) * self.dT + q.get(sc, 0.0) * X0 * self.dT
            Y += q.get(zy, 0.0) * self.dT + q.get(sc, 0.0) * Y0 * self.dT
        if "time_drift" in effects and self.t_h is not None:
            q = p["time_drift"]
            rx, ry = self.names["time_drift"]
            X += q.get(rx, 0.0) * self.t_h
            Y += q.get(ry, 0.0) * self.t_h
        return np.column_stack([X, Y])

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
            p = self.unpack(blocks, x)
            tx, ty = self.stage_angles(effects, p)
            u, v = self.map_inputs(effects, p, tx, ty)
            H = fit_projective(
                u / self.s,
                v / self.s,
                self.observed[:, 0] / self.s,
                self.observed[:, 1] / self.s,
                refine=False,
                what=f"{self.data.sensor} readings against stage angles",
            )
            x[:8] = H.ravel()[:8]
        return x

    # -- reporting
    # -----------------------------------------------------------------------------------
    def magnitude(self, fit: Fit, effect: str) -> dict[str, Any]:
        return stage_magnitude(self, fit, effect)


def _entry(value: float, std: float, unit: str, doc: str | None = None) -> dict[str, Any]:
    d = {"value": float(value), "uncertainty": float(std), "unit": unit}
    if doc:
        d["what"] = doc
    return d


def stage_magnitude(fam: OnStageData, fit: Fit, effect: str) -> dict[str, Any]:
    """Fitted parameters of one effect, in the registry's names and units where it has them."""
    sl = fit.block_slice(effect)
    blk = fit.block(effect)
    vals = fit.values[sl]
    cov = fit.covariance[sl, sl]
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    out: dict[str, Any] = {}
    if effect == "periodic_error":
        for ax in ("x", "y"):
            ls, lc = f"{ax}_sin_deg", f"{ax}_cos_deg"
            if ls not in blk.labels or lc not in blk.labels:
                # one of the pair held (the points sample too few phases of the worm): no amplitude
                continue
            i, j = blk.labels.index(ls), blk.labels.index(lc)
            a, b = vals[i], vals[j]
            amp = float(np.hypot(a, b))
            g = np.array([a, b]) / amp if amp > 0 else np.array([1.0, 0.0])
            c2 = cov[np.ix_([i, j], [i, j])]
            u_amp = float(np.sqrt(max(float(g @ c2 @ g), 0.0)))
            gp = np.array([-b, a]) / amp**2 if amp > 0 else np.zeros(2)
            u_ph = float(np.degrees(np.sqrt(max(float(gp @ c2 @ gp), 0.0)))) if amp > 0 else 180.0
            period = (
                fam.data.bench.worm_period_x_deg if ax == "x" else fam.data.bench.worm_period_y_deg
            )
            out[f"{ax}_amp_deg"] = _entry(
                amp, u_amp, "deg", f"amplitude at the worm period {period:g} deg"
            )
            out[f"{ax}_phase_deg"] = _entry(float(np.degrees(np.arctan2(b, a))), u_ph, "deg")
        return out
    for lab, unit, v, s in zip(blk.labels, blk.units, vals, std):
        out[lab] = _entry(v, s, unit)
    if effect == "offaxis_coupling" and "kappa" in out:
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
    return out
