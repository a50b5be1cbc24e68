"""Seed 004 rerun: inclinometer parameters β, m1, m2, ε from symmetric pairs, and the effect of the
assumed φ.

Writes seed004.md: the calibration on the simulated seed004 bench against the truth, the
parameters against the assumed rotation φ (the paper's Fig. 4), the β-φ ambiguity, and what
it means for the corrected axis tilt.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TypedDict

import numpy as np
from numpy.typing import NDArray

from service.calibration.model import CalibrationModel
from service.calibration.registry import FitOptions, Method, get_method
from service.calibration.uncertainty import coverage_factor
from service.io.datasets import write_text_atomic
from service.reproduce._report_kit import md_table, new_figure, of_kind, save_figure
from service.scenarios import load_scenario, run_scenario
from service.scenarios.model import TurntableScenario, parse_scenario

PARAMS = ("beta_deg", "m1_per_arcsec", "m2_per_arcsec", "epsilon_deg")
PHI_SWEEP = np.arange(175.0, 185.01, 0.5)


class Seed004Result(TypedDict):
    """The headline numbers `run` returns beside the report."""

    beta_per_phi_slope: float  # deg of beta per deg of assumed rotation
    beta_shift_for_1deg: float  # mean over the seeds, deg
    fit_at_180: dict[str, tuple[float, float | None]]  # per parameter: value, standard uncertainty
    truth: dict[str, float]
    residual_rms_spread: float
    corrected_spread_arcsec: float
    iterations_from_rough: int
    epsilon_spread: float
    m1_at_180: float
    figures: list[str]


def _fit(cols: Mapping[str, NDArray[np.float64]], phi: float) -> CalibrationModel:
    return get_method("turntable", "reversal").fit(cols, FitOptions(rotation_deg=float(phi)))


def _corrected_spread(
    method: Method, sweep: list[CalibrationModel], cols: Mapping[str, NDArray[np.float64]]
) -> float:
    """Largest difference of the corrected axis tilt between the fits of the φ sweep, north or
    east, against the first: the β-φ ambiguity does not reach the corrected tilt."""
    corrected = [method.correct(model, cols) for model in sweep]
    spread_corr = max(
        float(np.max(np.abs(tilt["north_arcsec"] - corrected[0]["north_arcsec"])))
        for tilt in corrected
    )
    return max(
        spread_corr,
        max(
            float(np.max(np.abs(tilt["east_arcsec"] - corrected[0]["east_arcsec"])))
            for tilt in corrected
        ),
    )


def _beta_shifts(data: Mapping[str, object], n_seeds: int) -> NDArray[np.float64]:
    """β fitted with φ = 180° minus β fitted with φ = 181°, on `n_seeds` runs of the bench in
    `data` (one that really turns 181°)."""
    shift_list = []
    for seed in range(n_seeds):
        columns = run_scenario(parse_scenario(data), seed=seed).columns
        shift_list.append(
            _fit(columns, 180.0).value("beta_deg") - _fit(columns, 181.0).value("beta_deg")
        )
    return np.array(shift_list)


def _fig4_parameters(
    out_dir: Path,
    vals: dict[str, NDArray[np.float64]],
    sds: dict[str, NDArray[np.float64]],
    truth: dict[str, float],
) -> str:
    """Like the paper's Fig. 4: each parameter against the assumed φ, beside the bench's truth."""
    fig, axes = new_figure(2, 2, (10, 7.5))
    labels = {
        "beta_deg": "(a) installation angle β / deg",
        "m1_per_arcsec": "(b) scale factor m1 / (mrad/″)",
        "m2_per_arcsec": "(c) scale factor m2 / (mrad/″)",
        "epsilon_deg": "(d) non-orthogonality ε / deg",
    }
    for ax, name in zip(axes.ravel(), PARAMS):
        ax.errorbar(
            PHI_SWEEP, vals[name], yerr=2 * sds[name], fmt="o-", ms=3, capsize=2, label="fit (±2u)"
        )
        ax.axhline(truth[name], color="tab:red", ls="--", lw=1, label="bench truth")
        ax.set(title=labels[name], xlabel="assumed rotation φ / deg")
        ax.legend(loc="best", fontsize=8)
    fig_name = "seed004_fig4_parameters_vs_phi.png"
    save_figure(fig, out_dir / fig_name)
    return fig_name


def _residuals_figure(
    out_dir: Path, base: CalibrationModel, cols: Mapping[str, NDArray[np.float64]]
) -> str:
    """The residuals of the calibration at φ = 180°, pair by pair, cycles side by side."""
    fig, ax = new_figure(1, 1, (7, 4))
    residuals = base.residuals["columns"]
    ax.plot(
        cols["azimuth_deg"] + 3 * cols["cycle"],
        residuals["north_arcsec"]["values"],
        "o",
        label="north (ξ)",
    )
    ax.plot(
        cols["azimuth_deg"] + 3 * cols["cycle"],
        residuals["east_arcsec"]["values"],
        "s",
        label="east (η)",
    )
    ax.axhline(0, color="0.6", lw=0.8)
    ax.set(
        title="residuals of the calibration at φ = 180° (reference minus model)",
        xlabel="azimuth of the pair / deg (cycles offset by 3°)",
        ylabel="arcsec",
    )
    ax.legend()
    res_name = "seed004_residuals.png"
    save_figure(fig, out_dir / res_name)
    return res_name


def _param_row(
    base: CalibrationModel, truth: dict[str, float], k95: float, n: str, fmt: str
) -> list[str]:
    """One parameter's row of the calibration table: truth, fitted value, U and the normalised
    error."""
    value, uncertainty = base.value(n), base.std(n)
    assert uncertainty is not None  # the reversal fit has a covariance for every parameter
    return [
        n,
        fmt.format(truth[n]),
        fmt.format(value),
        fmt.format(k95 * uncertainty),
        f"{(value - truth[n]) / uncertainty:+.2f}",
    ]


def _sweep_rows(vals: dict[str, NDArray[np.float64]], rms: NDArray[np.float64]) -> list[list[str]]:
    """The rows of the φ table: the fitted parameters and residual rms at every whole degree."""
    return [
        [
            f"{phi:.1f}",
            f"{vals['beta_deg'][i]:.4f}",
            f"{vals['m1_per_arcsec'][i]:.7f}",
            f"{vals['m2_per_arcsec'][i]:.7f}",
            f"{vals['epsilon_deg'][i]:.4f}",
            f"{rms[i]:.6f}",
        ]
        for i, phi in enumerate(PHI_SWEEP)
        if abs(phi - round(phi)) < 1e-9
    ]


def run(out_dir: Path) -> Seed004Result:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    sc = of_kind(load_scenario("seed004"), TurntableScenario)
    bench = sc.bench
    truth = {
        "beta_deg": bench.beta_deg,
        "m1_per_arcsec": bench.m1,
        "m2_per_arcsec": bench.m2,
        "epsilon_deg": bench.epsilon_deg,
    }
    run0 = run_scenario(sc)
    cols = run0.columns
    method = get_method("turntable", "reversal")
    base = _fit(cols, 180.0)

    # the paper's Fig. 4: parameters against the assumed φ
    sweep = [_fit(cols, phi) for phi in PHI_SWEEP]
    vals = {n: np.array([model.value(n) for model in sweep]) for n in PARAMS}
    sds = {n: np.array([model.std(n) for model in sweep]) for n in PARAMS}
    rms = np.array(
        [
            np.hypot(
                model.residuals["columns"]["north_arcsec"]["rms"],
                model.residuals["columns"]["east_arcsec"]["rms"],
            )
            for model in sweep
        ]
    )
    slope = float(np.polyfit(PHI_SWEEP, vals["beta_deg"], 1)[0])
    spread_corr = _corrected_spread(method, sweep, cols)

    # a bench that really turns 181°, calibrated with the usual assumption of 180°
    data = sc.model_dump()
    data["bench"]["rotation_deg"] = 181.0
    run181 = run_scenario(parse_scenario(data))
    wrong = _fit(run181.columns, 180.0)
    right = _fit(run181.columns, 181.0)
    n_seeds = 200
    shifts = _beta_shifts(data, n_seeds)

    # the paper's initial-value iteration: from rough start values
    rough = {"beta_deg": 0.0, "m1_per_arcsec": 0.005, "m2_per_arcsec": 0.005, "epsilon_deg": 0.0}
    from_rough = method.fit(cols, FitOptions(extra={"initial": rough}))

    fig_name = _fig4_parameters(out_dir, vals, sds, truth)
    res_name = _residuals_figure(out_dir, base, cols)

    k95 = float(coverage_factor(base.fit["dof"]))

    i180 = int(np.argmin(np.abs(PHI_SWEEP - 180.0)))
    rel_m = {
        dphi_deg: 1.0 / np.cos(np.radians(dphi_deg) / 2.0) - 1.0 for dphi_deg in (1.0, 2.0, 5.0)
    }
    md = [
        "# Seed 004: inclinometer parameters from symmetric pairs, and the assumed rotation",
        "",
        (
            "Rerun of seed 004 §3 on the simulated `seed004` bench (Nivel210-like inclinometer "
            "in mrad, 0.2″ resolution; 6 levellings × 8 pairs at azimuths 0°, 45°, 90°, 135° as "
            "in the paper's 16-image cycle; star reference 0.3″) with `tiltlab calibrate --kind "
            "turntable --method reversal [--rotation-deg φ]`: half-differences of each pair, "
            "the compensation (ξ̂, η̂) they give, and Gauss-Newton steps on β, m1, m2, ε "
            "against the star reference (eqs. 9-11). The paper's own readings (its Table 1) did "
            "not survive the conversion of the text, so the bench is simulated with the "
            "parameters in the preset."
        ),
        "",
        "## Calibration at the nominal φ = 180°",
        "",
        md_table(
            ["parameter", "bench truth", "fitted", f"U (95 %, k = {k95:.2f})", "(fit - truth) / u"],
            [
                _param_row(base, truth, k95, "beta_deg", "{:.4f}"),
                _param_row(base, truth, k95, "m1_per_arcsec", "{:.7f}"),
                _param_row(base, truth, k95, "m2_per_arcsec", "{:.7f}"),
                _param_row(base, truth, k95, "epsilon_deg", "{:.4f}"),
            ],
        ),
        "",
        (
            f"Residual σ {base.fit['residual_sigma_arcsec']:.3f}″ on {base.fit['dof']} degrees of "
            "freedom (the star "
            "reference's 0.3″ dominates; estimated reference scatter "
            f"{base.fit['reference_sigma_arcsec']:.3f}″, "
            f"reading noise {base.fit['reading_sigma']:.5f} mrad from the half-sums). Converged in "
            f"{base.fit['iterations']} iterations from the linear start values; from the rough "
            "start values "
            'β = 0°, m = 0.005 mrad/″, ε = 0° (the paper\'s "assign initial values") in '
            f"{from_rough.fit['iterations']} iterations to the same values "
            "(largest difference "
            f"{np.max(np.abs(from_rough.values(PARAMS) - base.values(PARAMS))):.1e})."
        ),
        "",
        f"![residuals]({res_name})",
        "",
        "## Parameters against the assumed φ (the paper's Fig. 4)",
        "",
        f"![parameters vs phi]({fig_name})",
        "",
        md_table(
            [
                "assumed φ / deg",
                "β / deg",
                "m1 / (mrad/″)",
                "m2 / (mrad/″)",
                "ε / deg",
                "residual rms (north ⊕ east) / ″",
            ],
            _sweep_rows(vals, rms),
        ),
        "",
        (
            f"* β moves by {slope:+.6f}° per degree of assumed φ: a rotation error of 1° moves β "
            "by 0.5°, as seed 004 "
            '§3.2 finds ("旋转角度每改变1°,标定出来的安装角度β改变0.5°").'
        ),
        (
            "* m1 and m2 are symmetric about φ = 180° (they scale as 1/cos(Δφ/2): "
            f"+{rel_m[1.0]:.1e} relative at "
            f"Δφ = 1°, +{rel_m[2.0]:.1e} at 2°, +{rel_m[5.0]:.1e} at 5°), and ε does not move "
            "(spread "
            f"{np.ptp(vals['epsilon_deg']):.1e}°), the paper's other two observations. Reading its "
            "lost eq. (14) as "
            '"sum of the squared relative scale-factor errors below 10⁻⁶", the condition holds up '
            "to "
            f"Δφ ≈ {2 * np.degrees(np.arccos(1 / (1 + np.sqrt(0.5e-6)))):.1f}°, consistent with "
            "its 2° statement."
        ),
        (
            f"* The residuals are the same for every assumed φ (rms {rms.min():.9f}″ to "
            f"{rms.max():.9f}″): the data cannot tell β from φ. Only β + φ/2 and m·sin(φ/2) "
            "enter the half-differences, so a pair rotation of 180° + Δ is indistinguishable "
            "from β + Δ/2 with m·cos(Δ/2). The method therefore holds φ at the assumed value (a "
            "fixed parameter in MODEL.json) and says so in the model's notes instead of fitting "
            "it."
        ),
        (
            "* For the same reason the corrected axis tilt is the same whichever φ is assumed, "
            "as long as calibration and use assume the same one: `correct` on these pairs "
            f"differs by at most {spread_corr:.1e}″ across the sweep. β itself is only wrong by "
            "Δφ/2 if it is used outside the pair geometry."
        ),
        "",
        "## A turntable that really turns 181°",
        "",
        md_table(
            ["calibrated with", "β / deg", "m1 / (mrad/″)", "residual σ / ″"],
            [
                [
                    "φ = 180° (the usual assumption)",
                    f"{wrong.value('beta_deg'):.4f}",
                    f"{wrong.value('m1_per_arcsec'):.7f}",
                    f"{wrong.fit['residual_sigma_arcsec']:.4f}",
                ],
                [
                    "φ = 181° (the truth)",
                    f"{right.value('beta_deg'):.4f}",
                    f"{right.value('m1_per_arcsec'):.7f}",
                    f"{right.fit['residual_sigma_arcsec']:.4f}",
                ],
            ],
        ),
        "",
        (
            f"Over {n_seeds} simulated calibrations the β shift between the two assumptions is "
            f"{shifts.mean():.9f}° ± {shifts.std():.1e}°: exactly half the rotation error, for "
            "every noise draw, with nothing in the residuals to reveal it (true β = 32.5°)."
        ),
        "",
    ]
    write_text_atomic(out_dir / "seed004.md", "\n".join(md))
    return {
        "beta_per_phi_slope": slope,
        "beta_shift_for_1deg": float(shifts.mean()),
        "fit_at_180": {n: (base.value(n), base.std(n)) for n in PARAMS},
        "truth": truth,
        "residual_rms_spread": float(np.ptp(rms)),
        "corrected_spread_arcsec": spread_corr,
        "iterations_from_rough": from_rough.fit["iterations"],
        "epsilon_spread": float(np.ptp(vals["epsilon_deg"])),
        "m1_at_180": float(vals["m1_per_arcsec"][i180]),
        "figures": [fig_name, res_name],
    }
