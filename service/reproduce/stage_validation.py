"""Validation of stage methods on a simulated bench, against an oracle that knows the truth.

Definitions (used by the tests, the seed 000 report and the docs):

* levelling error = true table tilt reached when the stage executes the commanded angles
  (true bench, stage repeatability, pulse rounding) minus the target;
* correction error = tilt corrected from the measurement readings minus the true table tilt;
* flow error (seed 000 Fig. 12) = target minus the corrected measurement after levelling:
  what the lab sees in the automatic flow of Fig. 7;
* uncorrected (seed 000 Fig. 12, "before"): stages commanded to the target angles as they are,
  measurement sensor read raw.

The oracle levels with the true bench and corrects with the true measurement sensor. Every
model executes its commands with the same random draws (same generator seed, same call
order), so the comparison isolates what calibration gets wrong.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.calibration.methods.stage.chain import ChainModel
from service.calibration.methods.stage.common import newton_2d
from service.calibration.model import CalibrationModel
from service.calibration.registry import FitExtras, FitOptions, levelling_method
from service.physics.effects import EffectSet
from service.physics.inclinometer import apply_reading_errors
from service.physics.stage import StageBench, simulate_stage
from service.scenarios import run_scenario
from service.scenarios.model import StageScenario

STAGE_METHODS = ("homography", "coupling", "axis-transform", "kinematic")


class FitKwargs(TypedDict, total=False):
    """Fit options of one method, as `FitOptions` takes them."""

    rotation_deg: float
    loss: str
    extra: FitExtras


def paper_grid() -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Seed 000 §4.4: 9 x 9 targets at 3 deg over ±12 deg."""
    steps = np.arange(-12.0, 12.0 + 1e-9, 3.0)
    grid_x, grid_y = np.meshgrid(steps, steps)
    return grid_x.ravel(), grid_y.ravel()


def offset_grid() -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """8 x 8 targets at 3 deg over ±10.5 deg: between the calibration points."""
    steps = np.arange(-10.5, 10.5 + 1e-9, 3.0)
    grid_x, grid_y = np.meshgrid(steps, steps)
    return grid_x.ravel(), grid_y.ravel()


def noise_free(fx: EffectSet) -> EffectSet:
    """The same bench without its random parts (for the oracle's model of it)."""
    eff = {effect: dict(fx.values[effect]) for effect in fx.on if effect != "noise"}
    return EffectSet.from_mapping("stage", eff)


class Oracle:
    """Levels and corrects with the true parameters of a simulated bench."""

    def __init__(self, bench: StageBench, fx: EffectSet, temp_c: float | None = None):
        self.bench = bench
        self.fx = noise_free(fx)
        self.chain = ChainModel(bench, self.fx)
        self.temp_c = bench.temp_ref_c if temp_c is None else temp_c

    def level(
        self, tx: ArrayLike, ty: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return self.chain.level(tx, ty, 1.0, 1.0)

    def _meas(
        self, ax_deg: NDArray[np.float64], ay_deg: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], dict[str, NDArray[np.float64]]]:
        fx, dT = self.fx, self.temp_c - self.bench.temp_ref_c
        geo = self.chain.geometry.readings_deg(np.radians(ax_deg), np.radians(ay_deg))
        out = []
        for axis in ("x", "y"):
            out.append(
                apply_reading_errors(
                    geo[f"meas_{axis}"],
                    zero_deg=fx.get("zero_offset", f"meas_{axis}_deg"),
                    scale=fx.get("scale_factor", f"meas_{axis}"),
                    quad_per_deg=fx.get("sensor_nonlinearity", f"meas_{axis}_per_deg"),
                    temp_delta_k=dT,
                    zero_per_k=fx.get("temperature_drift", f"meas_{axis}_deg_per_k"),
                    scale_per_k=fx.get("temperature_drift", "meas_scale_per_k"),
                )
            )
        return out[0], out[1], geo

    def correct(
        self, meas_x: ArrayLike, meas_y: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Stage angles whose noise-free measurement readings match, then the true tilt there."""
        mx, my = np.asarray(meas_x, dtype=float), np.asarray(meas_y, dtype=float)
        sign = (
            -1.0 if self.bench.meas_flip == "y" else 1.0,
            -1.0 if self.bench.meas_flip == "x" else 1.0,
        )
        stage_x, stage_y = newton_2d(
            lambda u, v: self._meas(u, v)[:2], mx, my, sign[0] * mx, sign[1] * my
        )
        geo = self._meas(stage_x, stage_y)[2]
        return geo["tilt_x"], geo["tilt_y"]


def execute(
    bench: StageBench, fx: EffectSet, cmd_x: ArrayLike, cmd_y: ArrayLike, seed: int, temp_c: float
) -> dict[str, NDArray[np.float64]]:
    """The true bench runs the commands (approached from below) with this seed's noise draws."""
    n = np.size(cmd_x)
    return simulate_stage(
        bench,
        fx,
        cmd_x,
        cmd_y,
        np.ones(n),
        np.ones(n),
        np.full(n, temp_c),
        np.zeros(n),
        rng=np.random.default_rng(seed),
    )


def summary(ex: NDArray[np.float64], ey: NDArray[np.float64]) -> dict[str, float]:
    ix, iy = int(np.argmax(np.abs(ex))), int(np.argmax(np.abs(ey)))
    return {
        "rms_x": float(np.sqrt(np.mean(ex**2))),
        "rms_y": float(np.sqrt(np.mean(ey**2))),
        "max_x": float(np.abs(ex).max()),
        "max_y": float(np.abs(ey).max()),
        "signed_max_x": float(ex[ix]),
        "signed_max_y": float(ey[iy]),
    }


@dataclass
class SeedResult:
    seed: int
    targets: tuple[NDArray[np.float64], NDArray[np.float64]]
    # method -> kind -> (ex, ey)
    errors: dict[str, dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]] = field(
        default_factory=dict
    )
    models: dict[str, CalibrationModel] = field(default_factory=dict)

    def stats(
        self, method: str, kind: str, mask: NDArray[np.bool_] | None = None
    ) -> dict[str, float]:
        ex, ey = self.errors[method][kind]
        return summary(ex, ey) if mask is None else summary(ex[mask], ey[mask])


def evaluate_seed(
    scenario: StageScenario,
    seed: int,
    methods: Sequence[str | tuple[str, str, FitExtras]] = STAGE_METHODS,
    targets: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    fit_options: Mapping[str, FitKwargs] | None = None,
    keep_models: bool = False,
) -> SeedResult:
    """Calibrate each method on the scenario's run with `seed`, validate on fresh noise at
    `targets`.

    `methods` holds method names, or (label, method name, extra fit options) for variants;
    `fit_options` the fit options of a label.
    """
    cal = run_scenario(scenario, seed=seed)
    bench, fx = cal.bench, cal.effects
    assert fx is not None  # a stage run carries its effect set
    temp = float(scenario.environment.temp_c)
    tx, ty = targets if targets is not None else paper_grid()
    val_seed = 1_000_003 + 7919 * seed  # independent of the calibration draws
    oracle = Oracle(bench, fx, temp)
    out = SeedResult(seed, (tx, ty))
    # shared readings for the correction errors: the table at the targets (oracle-levelled)
    ox, oy = oracle.level(tx, ty)
    shared = execute(bench, fx, ox, oy, val_seed + 1, temp)
    corr: dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}
    for spec in methods:
        label, name, extra = (spec, spec, {}) if isinstance(spec, str) else spec
        m = levelling_method("stage", name)
        given = (fit_options or {}).get(label, FitKwargs())
        opts: FitKwargs = {**given, "extra": {**given.get("extra", {}), **extra}}
        model = m.fit(cal.columns, FitOptions(**opts))
        if keep_models:
            out.models[label] = model
        cmd = m.level(model, {"target_x_deg": tx, "target_y_deg": ty})
        run = execute(bench, fx, cmd["stage_x_deg"], cmd["stage_y_deg"], val_seed, temp)
        own = m.correct(model, {"meas_x_deg": run["meas_x_deg"], "meas_y_deg": run["meas_y_deg"]})
        shared_corrected = m.correct(
            model, {"meas_x_deg": shared["meas_x_deg"], "meas_y_deg": shared["meas_y_deg"]}
        )
        corr[label] = (
            shared_corrected["tilt_x_deg"] - shared["tilt_x_deg"],
            shared_corrected["tilt_y_deg"] - shared["tilt_y_deg"],
        )
        out.errors[label] = {
            "level": (run["tilt_x_deg"] - tx, run["tilt_y_deg"] - ty),
            "correct": corr[label],
            "flow": (tx - own["tilt_x_deg"], ty - own["tilt_y_deg"]),
        }
    run = execute(bench, fx, ox, oy, val_seed, temp)
    cx, cy = oracle.correct(run["meas_x_deg"], run["meas_y_deg"])
    sx, sy = oracle.correct(shared["meas_x_deg"], shared["meas_y_deg"])
    out.errors["oracle"] = {
        "level": (run["tilt_x_deg"] - tx, run["tilt_y_deg"] - ty),
        "correct": (sx - shared["tilt_x_deg"], sy - shared["tilt_y_deg"]),
        "flow": (tx - cx, ty - cy),
    }
    raw = execute(bench, fx, tx, ty, val_seed, temp)
    out.errors["uncorrected"] = {
        "level": (raw["tilt_x_deg"] - tx, raw["tilt_y_deg"] - ty),
        "correct": (
            shared["meas_x_deg"] - shared["tilt_x_deg"],
            shared["meas_y_deg"] - shared["tilt_y_deg"],
        ),
        "flow": (tx - raw["meas_x_deg"], ty - raw["meas_y_deg"]),
    }
    return out


def oracle_ratios(
    result: SeedResult, method: str = "kinematic", mask: NDArray[np.bool_] | None = None
) -> dict[str, float]:
    """RMS and max of `method` over the oracle's, per error kind and axis."""
    out: dict[str, float] = {}
    for kind in ("level", "correct"):
        method_stats, oracle_stats = (
            result.stats(method, kind, mask),
            result.stats("oracle", kind, mask),
        )
        for stat in ("rms_x", "rms_y", "max_x", "max_y"):
            out[f"{kind}_{stat}"] = method_stats[stat] / oracle_stats[stat]
    return out
