"""Seed 004 rerun: inclinometer parameters β, m1, m2, ε from symmetric pairs, and the effect of the
assumed φ.

Writes seed004.md: the calibration on the simulated seed004 bench against the truth, the
parameters against the assumed rotation φ (the paper's Fig. 4), the β-φ ambiguity, and what
it means for the corrected axis tilt.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.calibration.model import CalibrationModel
from service.calibration.registry import FitOptions, get_method
from service.calibration.uncertainty import coverage_factor
from service.io.datasets import write_text_atomic
from service.reproduce._report_kit import md_table, new_figure, of_kind, save_figure
from service.scenarios import load_scenario, run_scenario
from service.scenarios.model import TurntableScenario, parse_scenario

PARAMS = ("beta_deg", "m1_per_arcsec", "m2_per_arcsec", "epsilon_deg")
PHI_SWEEP = np.arange(175.0, 185.01, 0.5)


def _fit(cols: Mapping[str, NDArray[np.float64]], phi: float) -> CalibrationModel:
    return get_method("turntable", "reversal").fit(cols, FitOptions(rotation_deg=float(phi)))


def run(out_dir: Path) -> dict[str, Any]:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    sc = of_kind(load_scenario("seed004"), TurntableScenario)
    b = sc.bench
    truth = {
        "beta_deg": b.beta_deg,
        "m1_per_arcsec": b.m1,
        "m2_per_arcsec": b.m2,
        "epsilon_deg": b.epsilon_deg,
    }
    run0 = run_scenario(sc)
    cols = run0.columns
    method = get_method("turntable", "reversal")
    base = _fit(cols, 180.0)

    # the paper's Fig. 4: parameters against the assumed φ
    sweep = [_fit(cols, p) for p in PHI_SWEEP]
    vals = {n: np.array([f.value(n) for f in sweep]) for n in PARAMS}
    sds = {n: np.array([f.std(n) for f in sweep]) for n in PARAMS}
    rms = np.array(
        [
            np.hypot(
                f.residuals["columns"]["north_arcsec"]["rms"],
                f.residuals["columns"]["east_arcsec"]["rms"],
            )
            for f in sweep
        ]
    )
    slope = float(np.polyfit(PHI_SWEEP, vals["beta_deg"], 1)[0])
    corrected = [method.correct(f, cols) for f in sweep]
    spread_corr = max(
        float(np.max(np.abs(c["north_arcsec"] - corrected[0]["north_arcsec"]))) for c in corrected
    )
    spread_corr = max(
        spread_corr,
        max(
            float(np.max(np.abs(c["east_arcsec"] - corrected[0]["east_arcsec"]))) for c in corrected
        ),
    )

    # a bench that really turns 181°, calibrated with the usual assumption of 180°
    data = sc.model_dump()
    data["bench"]["rotation_deg"] = 181.0
    run181 = run_scenario(parse_scenario(data))
    wrong = _fit(run181.columns, 180.0)
    right = _fit(run181.columns, 181.0)
    n_seeds = 200
    shift_list = []
    for seed in range(n_seeds):
        c = run_scenario(parse_scenario(data), seed=seed).columns
        shift_list.append(_fit(c, 180.0).value("beta_deg") - _fit(c, 181.0).value("beta_deg"))
    shifts = np.array(shift_list)

    # the paper's initial-value iteration: from rough start values
    rough = {"beta_deg": 0.0, "m1_per_arcsec": 0.005, "m2_per_arcsec": 0.005, "epsilon_deg": 0.0}
    from_rough = method.fit(cols, FitOptions(extra={"initial": rough}))

    # figure like Fig. 4
    fig, axes = new_figure(2, 2, (10, 7.5))
    labels = {
        "beta_deg": "(a) installation angle β / deg",
        "m1_per_arcsec": "(b) scale factor m1 / (mrad/″)",
        "m2_per_arcsec": "(c) scale factor m2 / (mrad/″)",
        "epsilon_deg": "(d) non-orthogonality ε / deg",
    }
    for ax, n in zip(axes.ravel(), PARAMS):
        ax.errorbar(
            PHI_SWEEP, vals[n], yerr=2 * sds[n], fmt="o-", ms=3, capsize=2, label="fit (±2u)"
        )
        ax.axhline(truth[n], color="tab:red", ls="--", lw=1, label="bench truth")
        ax.set(title=labels[n], xlabel="assumed rotation φ / deg")
        ax.legend(loc="best", fontsize=8)
    fig_name = "seed004_fig4_parameters_vs_phi.png"
    save_figure(fig, out_dir / fig_name)

    fig, ax = new_figure(1, 1, (7, 4))
    r = base.residuals["columns"]
    ax.plot(
        cols["azimuth_deg"] + 3 * cols["cycle"], r["north_arcsec"]["values"], "o", label="north (ξ)"
    )
    ax.plot(
        cols["azimuth_deg"] + 3 * cols["cycle"], r["east_arcsec"]["values"], "s", label="east (η)"
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

    def prow(n: str, fmt: str) -> list[str]:
        v, u = base.value(n), base.std(n)
        assert u is not None  # the reversal fit has a covariance for every parameter
        return [
            n,
            fmt.format(truth[n]),
            fmt.format(v),
            fmt.format(k95 * u),
            f"{(v - truth[n]) / u:+.2f}",
        ]

    k95 = float(coverage_factor(base.fit["dof"]))

    i180 = int(np.argmin(np.abs(PHI_SWEEP - 180.0)))
    rel_m = {d: 1.0 / np.cos(np.radians(d) / 2.0) - 1.0 for d in (1.0, 2.0, 5.0)}
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
                prow("beta_deg", "{:.4f}"),
                prow("m1_per_arcsec", "{:.7f}"),
                prow("m2_per_arcsec", "{:.7f}"),
                prow("epsilon_deg", "{:.4f}"),
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
            [
                [
                    f"{p:.1f}",
                    f"{vals['beta_deg'][i]:.4f}",
                    f"{vals['m1_per_arcsec'][i]:.7f}",
                    f"{vals['m2_per_arcsec'][i]:.7f}",
                    f"{vals['epsilon_deg'][i]:.4f}",
                    f"{rms[i]:.6f}",
                ]
                for i, p in enumerate(PHI_SWEEP)
                if abs(p - round(p)) < 1e-9
            ],
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
