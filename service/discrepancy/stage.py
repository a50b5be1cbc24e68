"""The discrepancy workflow on stacked swing-stage data (kind `stage`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.discrepancy import noise as noise_mod
from service.discrepancy.model import Family
from service.discrepancy.report_types import DiscrepancyReport, ReportExtra, ReportInputs
from service.discrepancy.stage_data import (
    StageData,
    common_skips,
    largest_residuals,
    stage_structure,
)
from service.discrepancy.workflow import DEFAULT_ALPHA, Result, find_missing_effects, to_report
from service.errors import InputError
from service.physics.stage import ASSUMED_BENCH_SOURCE, StageBench

if TYPE_CHECKING:
    from service.discrepancy.stage_kinematic_baseline import StageKinematic
    from service.discrepancy.stage_linear_baseline import StageLinear


def stage_noise(
    data: StageData, spec_sigma: ArrayLike | noise_mod.NoiseLevel | None = None
) -> noise_mod.NoiseLevel | None:
    """Repeated points first, then the stated noise level (the instrument specification, or a
    NoiseLevel the caller measured); None means 'from the final residual'."""
    if isinstance(spec_sigma, noise_mod.NoiseLevel):
        stated: noise_mod.NoiseLevel | None = spec_sigma
        spec_sigma = spec_sigma.sigma
    else:
        stated = None
    if data.point is not None:
        keys = [data.point]
        for direction in (data.dir_x, data.dir_y):
            if direction is not None:
                keys.append(direction)
        repeats = noise_mod.from_repeats(data.observed, np.column_stack(keys))
        if repeats is not None:
            return repeats
    if spec_sigma is not None:
        sigma_per_axis = np.broadcast_to(np.asarray(spec_sigma, dtype=float), (2,)).copy()
        if np.any(sigma_per_axis <= 0) or not np.all(np.isfinite(sigma_per_axis)):
            raise InputError(f"noise level must be positive, got {sigma_per_axis.tolist()}")
        if stated is not None:
            return noise_mod.NoiseLevel(sigma_per_axis, stated.source, stated.df, stated.detail)
        return noise_mod.from_specification(sigma_per_axis)
    return None


def _explain_drop(data: StageData) -> Callable[[str, str], str | None]:
    def explain(effect: str, label: str) -> str | None:
        ax = label[:1]
        if effect == "backlash" and ax in "xy":
            if data.dir(ax) is None:
                return f"no dir_{ax} column"
            if not data.both_directions(ax):
                return (
                    f"every point was reached moving the {ax} stage the same way (dir_{ax} has "
                    "one sign)"
                )
        if effect == "periodic_error" and ax in "xy":
            return (
                f"the grid samples the {ax} stage's worm at too few phases to tell its periodic "
                "error from a "
                "constant or a scale (grid step a whole or half number of worm turns)"
            )
        return None

    return explain


def _check_analysable(data: StageData, bench: StageBench | None) -> None:
    """Refuse data the workflow cannot judge: commands of another bench than the assumed one, or
    too few rows for a baseline and a test."""
    if (
        bench is None
        and (mismatch := data.bench.pulse_mismatch(data.cmd_x_deg, data.cmd_y_deg)) is not None
    ):
        raise InputError(
            f"{mismatch}. The worm period and the pulse quantisation of the stage model depend "
            f"on the bench's hardware and none was stated ({data.bench.describe()} assumed): "
            "give the bench the data came from with --bench FILE"
        )
    if len(data) < 6:
        raise InputError(
            f"{len(data)} rows: the discrepancy workflow needs at least 6 points for a baseline "
            "and a test"
        )


def _baseline_family(
    baseline: str, data: StageData, weights: NDArray[np.float64]
) -> StageLinear | StageKinematic:
    """The model family the named baseline starts from (imported on demand: each is heavy)."""
    if baseline == "linear":
        from service.discrepancy.stage_linear_baseline import StageLinear

        return StageLinear(data, weights)
    if baseline == "kinematic":
        from service.discrepancy.stage_kinematic_baseline import StageKinematic

        return StageKinematic(data, weights)
    raise InputError(f"unknown baseline {baseline!r} for kind 'stage' (linear or kinematic)")


def analyse_stage(
    columns: Mapping[str, NDArray[np.float64]],
    sensor: str = "ref",
    baseline: str = "linear",
    noise_sigma: ArrayLike | noise_mod.NoiseLevel | None = None,
    bench: StageBench | None = None,
    alpha: float = DEFAULT_ALPHA,
    candidates: tuple[str, ...] | None = None,
    bench_source: str | None = None,
) -> tuple[Result, Family]:
    """Run the workflow on stage columns; returns the result and the fitted family (for the
    report)."""
    data = StageData.from_columns(columns, sensor, bench)
    _check_analysable(data, bench)
    noise = stage_noise(data, noise_sigma)
    weights = np.ones(2) if noise is None or noise.sigma is None else 1.0 / noise.sigma
    fam = _baseline_family(baseline, data, weights)
    fam.noise_known = noise is not None
    cands = tuple(effect for effect in (candidates or fam.candidates) if effect in fam.candidates)
    skips = common_skips(data)
    res = find_missing_effects(
        fam,
        cands,
        skips,
        noise or noise_mod.NoiseLevel(None, "final residual", np.inf, ""),
        lambda r: stage_structure(data, r),
        alpha=alpha,
        explain_drop=_explain_drop(data),
    )
    res.extra["where_largest"] = largest_residuals(data, res.fits[0].residuals)
    res.extra["bench"] = data.bench.record(
        bench_source or (ASSUMED_BENCH_SOURCE if bench is None else "stated by the caller")
    )
    extra: ReportExtra = getattr(fam, "report_extra", ReportExtra())  # the kinematic baseline's
    res.extra.update(extra)
    return res, fam


def stage_report(
    columns: Mapping[str, NDArray[np.float64]],
    sensor: str = "ref",
    baseline: str = "linear",
    noise_sigma: ArrayLike | noise_mod.NoiseLevel | None = None,
    bench: StageBench | None = None,
    alpha: float = DEFAULT_ALPHA,
    inputs: ReportInputs | None = None,
    bench_source: str | None = None,
) -> tuple[DiscrepancyReport, Result, Family]:
    res, fam = analyse_stage(
        columns, sensor, baseline, noise_sigma, bench, alpha, bench_source=bench_source
    )
    rep = to_report(res, fam, {"sensor": sensor, "n_rows": len(fam.observed), **(inputs or {})})
    return rep, res, fam


def stage_diagnosis(
    columns: Mapping[str, NDArray[np.float64]],
    sensor: str = "ref",
    baseline: str = "linear",
    noise_sigma: ArrayLike | noise_mod.NoiseLevel | None = None,
    bench: StageBench | None = None,
    inputs: ReportInputs | None = None,
    bench_source: str | None = None,
    provenance: Mapping[str, object] | None = None,
) -> tuple[DiscrepancyReport, str, Result, Family]:
    """The whole workflow on stage columns as `tiltlab discrepancy` and the daemon's diagnosis run
    it: the JSON-ready report (with its provenance) and its HTML page, plus the result and fitted
    family behind them."""
    from service.discrepancy.report import clean_report, render_html

    report, result, fam = stage_report(
        columns, sensor, baseline, noise_sigma, bench, inputs=inputs, bench_source=bench_source
    )
    if provenance is not None:
        report["provenance"] = provenance
    report = clean_report(report)
    return report, render_html(report, result, fam), result, fam
