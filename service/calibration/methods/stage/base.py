"""What every stage method shares: the columns, the bench it was calibrated for, the levelling
output (refused beyond the bench's travel), the statistics and the GUM correction helper."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from service.calibration.differences import central_jacobian
from service.calibration.methods.stage.common import (
    MEAS_COLUMNS,
    REF_COLUMNS,
    STAGE_COLUMNS,
    TILT_OUTPUTS,
    columns,
    detect_mirror,
    sign_from_options,
)
from service.calibration.model import (
    CalibrationModel,
    FitStats,
    ModelState,
    Parameter,
    StageBenchJSON,
)
from service.calibration.reading_noise import ReadingNoise
from service.calibration.registry import FitOptions
from service.calibration.uncertainty import coverage_factor, propagate_gum
from service.errors import DegenerateDataError, InputError
from service.io.columns import K_OUTPUTS
from service.physics.stage import ASSUMED_BENCH_SOURCE, StageBench

Columns = Mapping[str, NDArray[np.float64]]
FIT_REQUIRED = STAGE_COLUMNS + REF_COLUMNS
FIT_OPTIONAL = MEAS_COLUMNS + (
    "dir_x",
    "dir_y",
    "temp_c",
    "t_s",
    "point",
    "noise_ref_x_deg",
    "noise_ref_y_deg",
)
CROSS_TOL_DEG = 1e-6


def stage_hardware(options: FitOptions) -> tuple[StageBench, str, bool]:
    """The bench the data came from: stated by the caller (options.extra["bench"]) or assumed (seed
    000's)."""
    given = options.extra.get("bench")
    if given is None:
        return StageBench(), ASSUMED_BENCH_SOURCE, False
    bench = given if isinstance(given, StageBench) else StageBench(**given)
    return bench, str(options.extra.get("bench_source", "stated by the caller")), True


def bench_state(bench: StageBench, source: str) -> ModelState:
    """What a stage model keeps of its bench: the hardware (levelling's travel, the kinematic chain)
    and its source."""
    # StageBenchJSON states StageBench's fields
    return {"bench": cast(StageBenchJSON, asdict(bench)), "bench_source": source}


def meas_sign(data: Columns, options: FitOptions) -> tuple[NDArray[np.float64], str]:
    mx, my, rx, ry = columns(data, MEAS_COLUMNS + REF_COLUMNS)
    return sign_from_options(options.extra, detect_mirror(mx, my, rx, ry))


def fit_stats(r: NDArray[np.float64], n_par: int) -> FitStats:
    """Degrees of freedom and residual sigma; no sigma when the points only just determine the
    parameters."""
    dof = r.size - n_par
    return {"dof": dof, "sigma_deg": float(np.sqrt(r @ r / dof)) if dof > 0 else None}


def _pooled_ref_variance(data: Columns, sign: NDArray[np.float64]) -> tuple[float, float] | None:
    """The reference's own reading variance from repeated rows at one point, and its degrees of
    freedom.

    Within a point, the reference varies by its noise and by the stage's positioning error (from one
    move to the next); the measurement sensor sees the same table, so the positioning error is their
    within-point covariance: var(ref) - cov(ref, meas) leaves the reference's own noise. Pooled over
    the points and both axes, with Σ(n_i - 1) degrees of freedom per axis.
    """
    if "point" not in data:
        return None
    point = np.asarray(data["point"])
    _, which, counts = np.unique(point, return_inverse=True, return_counts=True)
    dof = int(np.sum(counts - 1))
    if dof < 2:
        return None
    var = cov = 0.0
    for ref, m, sg in (
        (data["ref_x_deg"], data["meas_x_deg"], sign[0]),
        (data["ref_y_deg"], data["meas_y_deg"], sign[1]),
    ):
        ref = np.asarray(ref, dtype=float)
        m = sg * np.asarray(m, dtype=float)
        dr = ref - (np.bincount(which, ref) / counts)[which]
        dm = m - (np.bincount(which, m) / counts)[which]
        var += float(dr @ dr)
        cov += float(dr @ dm)
    return (var - cov) / (2 * dof), float(2 * dof)


def _stated_ref_sigma(data: Columns, options: FitOptions) -> float | None:
    """The reference's noise (1 σ of one reading) as the data's `noise_ref_*` columns or the option
    ref_noise_deg state it."""
    cols = [column for column in ("noise_ref_x_deg", "noise_ref_y_deg") if column in data]
    if cols:
        return float(
            np.sqrt(
                np.mean([np.mean(np.asarray(data[column], dtype=float) ** 2) for column in cols])
            )
        )
    stated = options.extra.get("ref_noise_deg")
    if stated is None:
        return None
    value = float(stated)
    if not (np.isfinite(value) and value >= 0):
        raise InputError(
            f"option ref_noise_deg: {stated!r} is not a standard deviation in degrees (a "
            "number >= 0)"
        )
    return value


# the reading term is never taken below this fraction of the residual's variance
RESIDUAL_FLOOR = 0.1
# Below this many points the three-way estimate of the reference's noise has a handful of degrees
# of freedom (9 points: about 2.5), and its coverage factor would swamp what it saves; the whole
# residual is taken instead. A count fixed in advance, not chosen by the estimate.
MIN_THREE_WAY_POINTS = 30


@dataclass(frozen=True)
class ThreeWay:
    """The three instruments that read one table at every point, as residuals (2 x n: x row, y row):
    the measurement sensor against the reference, in the reference's frame (its noise less the
    reference's), and the reference against the stage model's prediction (the reference's noise
    plus the stage's positioning error and whatever the stage model leaves out)."""

    meas_minus_ref_deg: NDArray[np.float64]
    ref_minus_stage_deg: NDArray[np.float64]


def meas_reading_noise(
    data: Columns,
    options: FitOptions,
    residual_sigma_deg: float,
    residual_dof: float,
    sign: NDArray[np.float64] | None = None,
    three_way: ThreeWay | None = None,
) -> ReadingNoise:
    """u of one measurement reading = √(s_residual² − σ_ref²), with σ_ref from repeats, as stated,
    or from the three-way comparison of stage, reference and measurement sensor.

    What the model does not describe stays in it (it is in the residual, not in σ_ref). With one
    reading per point and nothing stated, the reference's noise is the one thing the meas-vs-ref
    residual shares with the ref-vs-stage residual, with opposite signs: −cov of the two (Grubbs'
    three-instrument method); without a stage prediction the whole residual is taken (conservative:
    about √2 too large for two equal sensors). The source says which. Degrees of freedom by
    Welch-Satterthwaite, or from the scatter of the three-way products.
    """
    sign = np.ones(2) if sign is None else np.asarray(sign, dtype=float)
    s2 = residual_sigma_deg**2
    pooled = _pooled_ref_variance(data, sign) if has_meas_columns(data) else None
    if pooled is not None:
        ref_var, ref_dof = max(pooled[0], 0.0), pooled[1]
        how = (
            "the reference's noise from the repeated readings at each point (var(ref) - "
            f"cov(ref, meas) within points, {ref_dof:.0f} degrees of freedom)"
        )
    elif (stated := _stated_ref_sigma(data, options)) is not None:
        ref_var, ref_dof = stated**2, np.inf
        how = f"the reference's stated noise {stated:.3g} deg"
    elif three_way is not None and _points_of(three_way) >= MIN_THREE_WAY_POINTS:
        return _three_way_noise(three_way, residual_sigma_deg, residual_dof)
    else:
        too_few = (
            f"; the three-way comparison with the stage needs at least {MIN_THREE_WAY_POINTS} "
            f"points, these data have {_points_of(three_way)}"
            if three_way is not None
            else ""
        )
        return ReadingNoise(
            residual_sigma_deg,
            residual_dof,
            "the whole meas-vs-ref residual (it also holds the reference's noise: conservative; "
            "repeated readings at the points or the reference's stated noise (noise_ref_* columns, "
            f"option ref_noise_deg) separate the two{too_few})",
        )
    var = s2 - ref_var
    floor = RESIDUAL_FLOOR * s2
    note = ""
    if var < floor:
        var, note = (
            floor,
            f" (floored at {RESIDUAL_FLOOR:g} of the residual's variance: the estimate left less)",
        )
    with np.errstate(divide="ignore"):
        denom = s2**2 / residual_dof + (ref_var**2 / ref_dof if np.isfinite(ref_dof) else 0.0)
    dof = float(var**2 / denom) if denom > 0 else float("inf")
    dof = min(dof, float(residual_dof))
    return ReadingNoise(
        float(np.sqrt(var)),
        dof,
        f"the meas-vs-ref residual ({residual_sigma_deg:.3g} deg) less {how}{note}",
        float(np.sqrt(ref_var)),
    )


def _points_of(three_way: ThreeWay) -> int:
    return int(np.asarray(three_way.meas_minus_ref_deg).shape[-1])


def _three_way_noise(
    three_way: ThreeWay, residual_sigma_deg: float, residual_dof: float
) -> ReadingNoise:
    """One measurement reading's noise with the reference's taken out by the three-way comparison.

    Per point, d = meas − ref ≈ e_meas − e_ref and r = ref − stage ≈ e_ref + e_stage: the mean of
    d·r is −σ_ref², whatever the stage's positioning error and the stage model's misfit (they are
    not in d). σ_meas² = (Σd² + Σd·r) / ν with ν the meas fit's degrees of freedom, floored like the
    other estimates; its own degrees of freedom 2 σ⁴ / var(σ̂²) from the scatter of d² + d·r (a
    noisy estimate is said to be one, and its coverage factor grows)."""
    d = np.asarray(three_way.meas_minus_ref_deg, dtype=float).ravel()
    r = np.asarray(three_way.ref_minus_stage_deg, dtype=float).ravel()
    s2 = residual_sigma_deg**2
    ref_var = -float(d @ r) / residual_dof
    var = s2 - ref_var
    note = ""
    if var < RESIDUAL_FLOOR * s2:
        var, note = (
            RESIDUAL_FLOOR * s2,
            f" (floored at {RESIDUAL_FLOOR:g} of the residual's variance: the estimate left less)",
        )
    products = d * d + d * r
    spread = float(np.var(products, ddof=1)) if products.size > 1 else 0.0
    dof = 2.0 * float(np.mean(products)) ** 2 / (spread / products.size) if spread > 0 else np.inf
    dof = float(min(max(dof, 1.0), residual_dof))
    ref_sigma = float(np.sqrt(max(ref_var, 0.0)))
    return ReadingNoise(
        float(np.sqrt(var)),
        dof,
        f"the meas-vs-ref residual ({residual_sigma_deg:.3g} deg) less the reference's noise from "
        "the three-way comparison of stage, reference and measurement sensor (one reading per "
        f"point: the reference's variance is -cov(meas - ref, ref - stage), {ref_sigma:.3g} deg, "
        f"{dof:.0f} degrees of freedom){note}",
        ref_sigma,
    )


def has_meas_columns(data: Columns) -> bool:
    return all(meas_column in data for meas_column in MEAS_COLUMNS)


def noise_state(noise: ReadingNoise) -> ModelState:
    """What a model keeps of the reading noise (MODEL.json state): standard uncertainties, named as
    such."""
    state: ModelState = {
        "meas_reading_standard_uncertainty_deg": noise.sigma_deg,
        "meas_reading_dof": noise.dof,
        "meas_reading_noise_source": noise.source,
    }
    if noise.ref_sigma_deg is not None:
        state["ref_reading_standard_uncertainty_deg"] = noise.ref_sigma_deg
    return state


def reading_noise_of(model: CalibrationModel) -> tuple[float, float]:
    """(u of one measurement reading, its degrees of freedom) of a model; models made before the two
    sensors' noise was separated state only the residual (`meas_sigma_deg`, `meas_dof`), read as
    before."""
    st = model.state
    if "meas_reading_standard_uncertainty_deg" in st:
        dof = st.get("meas_reading_dof")
        return float(st["meas_reading_standard_uncertainty_deg"]), float(dof) if dof else float(
            "inf"
        )
    # a model that kept no sigma has no meas_reading_* either: read as before (None is refused)
    return float(cast(float, st.get("meas_sigma_deg", 0.0))), meas_dof(model)


def numeric_cov(
    fun: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    p: NDArray[np.float64],
    scales: NDArray[np.float64],
    s2: float,
) -> NDArray[np.float64]:
    """Gauss-Newton covariance s²(JᵀJ)⁻¹ of parameters p of a residual function (scaled for
    conditioning)."""
    return jacobian_cov(central_jacobian(fun, p, scales), scales, s2)


def jacobian_cov(
    J: NDArray[np.float64], scales: NDArray[np.float64], s2: float
) -> NDArray[np.float64]:
    """s²(JᵀJ)⁻¹ from the residuals' Jacobian J (unscaled), scaled by `scales` for conditioning."""
    scaled = J * scales
    sv = np.linalg.svd(scaled, compute_uv=False)
    if sv[-1] <= 1e-10 * sv[0]:
        raise DegenerateDataError(
            "the points do not determine every parameter of the model (singular fit)"
        )
    cov: NDArray[np.float64] = np.linalg.inv(scaled.T @ scaled) * np.outer(scales, scales) * s2
    return cov


def uncertain_correct(
    f: Callable[[NDArray[np.float64], Mapping[str, NDArray[np.float64]]], NDArray[np.float64]],
    p: NDArray[np.float64],
    cov: NDArray[np.float64] | None,
    data: Columns,
    sigma_deg: float,
    dof: float,
    noise_dof: float | None = None,
) -> dict[str, NDArray[np.float64]]:
    """tilt = f(p, readings) and its expanded GUM uncertainty from cov and the reading noise.

    The covariance comes from a fit with `dof` degrees of freedom, the reading noise from an
    estimate with `noise_dof` (the same fit's when not given); the coverage factor follows from
    the Welch-Satterthwaite effective degrees of freedom (95 %).
    """
    inputs = {
        meas_column: np.asarray(data[meas_column], dtype=float) for meas_column in MEAS_COLUMNS
    }
    y = f(p, inputs)
    out = {"tilt_x_deg": y[:, 0], "tilt_y_deg": y[:, 1]}
    if cov is not None:
        gum = propagate_gum(
            f,
            p,
            cov,
            inputs,
            {meas_column: sigma_deg for meas_column in MEAS_COLUMNS},
            dof,
            dof if noise_dof is None else noise_dof,
        )
        expanded, k = gum.expanded(), np.broadcast_to(coverage_factor(gum.dof_eff), gum.u.shape)
        out["u_tilt_x_deg"], out["u_tilt_y_deg"] = expanded[:, 0], expanded[:, 1]
        out[K_OUTPUTS[0]], out[K_OUTPUTS[1]] = k[:, 0], k[:, 1]
    return out


def meas_dof(model: CalibrationModel) -> float:
    """Degrees of freedom of the measurement-sensor fit (infinite for models written before it was
    kept)."""
    dof = model.state.get("meas_dof")
    return float(dof) if dof else float("inf")


def stage_commands(
    model: CalibrationModel, x: NDArray[np.float64], y: NDArray[np.float64]
) -> dict[str, NDArray[np.float64]]:
    """Levelling output of every stage method: refused where the bench cannot go.

    The travel is the bench's the model was fitted for (the kinematic model keeps it), else the
    stacked bench of docs/models.md §2 (±15°).
    """
    travel = float(model.state.get("bench", {}).get("travel_deg", StageBench().travel_deg))
    bad = ~(np.isfinite(x) & np.isfinite(y))
    if bad.any():
        rows = ", ".join(str(i + 1) for i in np.flatnonzero(bad)[:5])
        raise InputError(
            f"target row(s) {rows}: no stage angles reach the wanted tilt under this model"
        )
    beyond = np.flatnonzero((np.abs(x) > travel) | (np.abs(y) > travel))
    if beyond.size:
        rows = ", ".join(str(i + 1) for i in beyond[:5])
        raise InputError(
            f"target row(s) {rows} need stage angles beyond the bench's travel of ±{travel:g} deg "
            f"(e.g. stage_x_deg {x[beyond[0]]:.3f}, stage_y_deg {y[beyond[0]]:.3f})"
        )
    return {"stage_x_deg": x, "stage_y_deg": y}


def targets(data: Columns) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    x, y = columns(data, ("target_x_deg", "target_y_deg"))
    return x, y


def stage_model(
    method: str, used: list[str], params: dict[str, Parameter], notes: list[str], **kw: Any
) -> CalibrationModel:
    return CalibrationModel(
        kind="stage", method=method, columns=used, parameters=params, notes=notes, **kw
    )


def used_columns(data: Columns) -> list[str]:
    return [column for column in FIT_REQUIRED + FIT_OPTIONAL if column in data]


class StageMethod:
    """A stage calibration: fit (data -> model), level (wanted tilt -> stage commands), correct
    (readings -> tilt).

    Subclasses give `fit`, `commands` (the unchecked stage angles for the targets) and `correct`;
    levelling's checks (reachable, within the bench's travel) are the same for every method.
    """

    kind = "stage"
    name = ""
    fit_required = FIT_REQUIRED
    fit_optional = FIT_OPTIONAL
    correct_required = MEAS_COLUMNS
    correct_optional = ()
    outputs = TILT_OUTPUTS

    def fit(self, data: Columns, options: FitOptions) -> CalibrationModel:
        raise NotImplementedError

    def commands(
        self, model: CalibrationModel, data: Columns
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Stage angles for the targets in `data`, before levelling's checks."""
        raise NotImplementedError

    def correct(self, model: CalibrationModel, data: Columns) -> dict[str, NDArray[np.float64]]:
        raise NotImplementedError

    def level(self, model: CalibrationModel, data: Columns) -> dict[str, NDArray[np.float64]]:
        x, y = self.commands(model, data)
        return stage_commands(model, x, y)
