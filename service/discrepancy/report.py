"""The report page: one self-contained HTML file (figures inline as PNG data URIs) showing the gap
shrink.

For people, next to the JSON for machines: the chain of named effects, the residual maps
before and after each step, the RMS of every stage of the chain against the noise level,
where the disagreement was and why the workflow stopped.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from service.discrepancy.model import Family, Fit
from service.discrepancy.report_types import CandidateScore, DiscrepancyReport, JSONValue
from service.discrepancy.scale import ScalePoly
from service.discrepancy.stage_kinematic_baseline import StageKinematic
from service.discrepancy.stage_linear_baseline import StageLinear
from service.io.figures import new_figure, png_data_uri

if TYPE_CHECKING:
    from service.discrepancy.workflow import Result

REPORT_SIGNIFICANT_DIGITS = 8


def clean(o: object) -> JSONValue:
    """JSON-safe: numpy scalars to Python, non-finite numbers to null, 8 significant digits."""
    if isinstance(o, dict):
        return {str(k): clean(value) for k, value in o.items()}
    if isinstance(o, (list, tuple)):
        return [clean(value) for value in o]
    if isinstance(o, (np.floating, float)):
        number = float(o)
        # 8 significant digits: more than any statistic or magnitude here is known to
        # (docs/models.md, "Digits")
        return float(f"{number:.{REPORT_SIGNIFICANT_DIGITS}g}") if math.isfinite(number) else None
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return clean(o.tolist())
    # str, int, bool and None are JSON already (anything else stays for json.dumps to refuse)
    return cast(JSONValue, o)


def clean_report(report: DiscrepancyReport) -> DiscrepancyReport:
    """`clean` over a whole report: the same keys in the same order, its numbers Python's, to 8
    significant digits (a non-finite one null, which the report's types do not spell out)."""
    return cast(DiscrepancyReport, clean(report))


def _figure(w: float, h: float, rows: int = 1, cols: int = 1, **_margins: float) -> tuple[Any, Any]:
    """A grid of axes from the one figure helper (constrained layout: margins are its business)."""
    return new_figure(rows, cols, (w, h), squeeze=False)


def _png(fig: Any) -> str:
    return png_data_uri(fig)


def _img(uri: str, alt: str) -> str:
    return f'<img src="{uri}" alt="{html.escape(alt)}">'


def _labels(report: DiscrepancyReport) -> list[str]:
    return [report["baseline"]] + [f"+ {step['effect']}" for step in report["steps"]]


def _rms_figure(report: DiscrepancyReport) -> str:
    labels = _labels(report)
    rms = np.array([report["baseline_rms"]] + [step["rms_after"] for step in report["steps"]])
    noise = np.array(report["noise_level"])
    fig, axs = _figure(6.5, 3.4, left=0.15, right=0.97, bottom=0.2, top=0.9)
    ax = axs[0, 0]
    width = 0.8 / rms.shape[1]
    x = np.arange(len(labels))
    for column, name in enumerate(report["axes"]):
        ax.bar(
            x + (column - (rms.shape[1] - 1) / 2) * width,
            rms[:, column],
            width,
            label=f"RMS {name}",
        )
        ax.axhline(
            noise[column],
            ls="--",
            lw=1,
            color=f"C{column}",
            label=f"noise {name} ({report['noise_source']})",
        )
    ax.set_xticks(x, labels, rotation=15)
    ax.set_yscale("log")
    ax.set_ylabel(f"residual RMS [{report['unit']}]")
    ax.set_title("the gap between model and measurement, step by step")
    ax.legend(fontsize=7)
    return _png(fig)


def _stage_maps(
    fam: StageLinear | StageKinematic, fits: Sequence[Fit], titles: Sequence[str], unit: str
) -> str:
    """All residual maps in one figure: a row per stage of the chain, x and y side by side."""
    x, y = fam.data.cmd_x_deg, fam.data.cmd_y_deg
    n = len(fits)
    height_in = 3.1 * n
    fig, axs = _figure(
        8.0,
        height_in,
        n,
        2,
        left=0.08,
        right=0.97,
        bottom=0.5 / height_in,
        top=1 - 0.35 / height_in,
        hspace=0.45,
        wspace=0.5,
    )
    for i, (fit, title) in enumerate(zip(fits, titles)):
        resid = fit.residuals
        for column, name in enumerate(("x", "y")):
            ax = axs[i, column]
            lim = float(np.max(np.abs(resid[:, column]))) or 1.0
            sc = ax.scatter(
                x,
                y,
                c=resid[:, column],
                cmap="RdBu_r",
                vmin=-lim,
                vmax=lim,
                s=50,
                edgecolors="k",
                linewidths=0.3,
            )
            ax.set_xlabel("stage x [deg]", fontsize=8)
            ax.set_ylabel("stage y [deg]", fontsize=8)
            ax.set_title(
                f"{title}: {name} residual, "
                f"RMS {np.sqrt(np.mean(resid[:, column] ** 2)):.3g} {unit}",
                fontsize=8,
            )
            ax.set_aspect("equal", adjustable="datalim")
            fig.colorbar(sc, ax=ax, label=unit, shrink=0.85)
    return _png(fig)


def _scale_plots(fam: ScalePoly, fits: Sequence[Fit], titles: Sequence[str], unit: str) -> str:
    n = len(fits)
    height_in = 2.4 * n
    fig, axs = _figure(
        6.0,
        height_in,
        n,
        1,
        left=0.14,
        right=0.97,
        bottom=0.45 / height_in,
        top=1 - 0.3 / height_in,
        hspace=0.6,
    )
    for i, (fit, title) in enumerate(zip(fits, titles)):
        ax = axs[i, 0]
        ax.axhline(0, color="k", lw=0.5)
        ax.plot(fam.reading, fit.residuals[:, 0], "o")
        ax.set_xlabel("sensor output [count]", fontsize=8)
        ax.set_ylabel(f"residual [{unit}]", fontsize=8)
        ax.set_title(
            f"{title}: RMS {np.sqrt(np.mean(fit.residuals[:, 0] ** 2)):.3g} {unit}", fontsize=9
        )
    return _png(fig)


def _histogram(report: DiscrepancyReport, fit: Fit) -> str:
    resid = fit.residuals
    noise = np.array(report["noise_level"])
    fig, axs = _figure(
        3.4 * resid.shape[1], 3.0, 1, resid.shape[1], left=0.1, right=0.97, bottom=0.18, top=0.85
    )
    for column, name in enumerate(report["axes"]):
        ax = axs[0, column]
        z = resid[:, column] / noise[column]
        ax.hist(z, bins=max(8, int(np.sqrt(z.size))), density=True, alpha=0.7)
        grid = np.linspace(-4, 4, 200)
        ax.plot(grid, np.exp(-(grid**2) / 2) / np.sqrt(2 * np.pi), "k-", lw=1)
        ax.set_xlabel(f"final {name} residual / noise level")
    fig.suptitle("final residual against the noise level (curve: the noise alone)", fontsize=9)
    return _png(fig)


def _table(rows: list[list[str]], head: list[str]) -> str:
    header = "".join(f"<th>{html.escape(cell)}</th>" for cell in head)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(str(cell))}</td>" for cell in row) + "</tr>"
        for row in rows
    )
    return f"<table><tr>{header}</tr>{body}</table>"


def _p(v: float | None) -> str:
    """A p-value; one below the smallest double (computed as 0) is shown as the bound it is."""
    if v is None:
        return "—"
    return "< 1e-300" if float(v) < 1e-300 else f"{float(v):.2g}"


def _fmt(v: object) -> str:
    if v is None:
        return "—"
    if isinstance(v, float):
        return f"{v:.3g}"
    if isinstance(v, list):
        return ", ".join(_fmt(x) for x in v)
    return str(v)


CSS = """body{font-family:sans-serif;max-width:1000px;margin:1em auto;color:#222}
table{border-collapse:collapse;margin:.5em 0;font-size:90%}
td,th{border:1px solid #bbb;padding:3px 6px;text-align:left}
th{background:#eee}img{max-width:100%}
.concl{background:#f4f8ff;border-left:4px solid #36c;padding:.5em 1em}
details{margin:.3em 0}code{background:#f3f3f3}"""


_esc = html.escape
_CANDIDATE_HEAD = ["statistic", "p", "ΔBIC", "significant"]


def render_html(report: DiscrepancyReport, result: Result, fam: Family) -> str:
    """The whole page as one string (no external resources)."""
    unit = report["unit"]
    parts = [
        (
            "<!doctype html><html><head><meta charset='utf-8'><title>tiltlab discrepancy: "
            f"{_esc(report['kind'])}</title><style>{CSS}</style></head><body>"
        )
    ]
    parts += _summary_section(report, unit)
    parts += _where_section(report)
    parts += _residuals_section(report, result, fam, unit)
    parts += _candidates_section(report, unit)
    parts += _not_tested_section(report)
    parts += _provenance_section(report)
    parts.append("</body></html>")
    return "\n".join(parts)


def _summary_section(report: DiscrepancyReport, unit: str) -> list[str]:
    """The page's top: the data, the conclusion, the chain of named effects, why it stopped,
    the noise level and the bench."""
    parts = [f"<h1>Where the {_esc(report['baseline'])} model and the measurement disagree</h1>"]
    src = report.get("input", "")
    parts.append(
        f"<p>Data: <code>{_esc(str(src))}</code>, kind <b>{_esc(report['kind'])}</b>"
        + (f", sensor <b>{_esc(report['sensor'])}</b>" if "sensor" in report else "")
        + f", {report.get('n_rows', '')} rows. Residual = measured − model, in {_esc(unit)}.</p>"
    )
    parts.append(f"<p class='concl'>{_esc(report['conclusion'])}</p>")
    parts.append("<h2>Chain of named effects</h2>")
    parts.append(_chain_table(report, unit))
    parts.append(f"<p><b>Stop:</b> {_esc(report['stop']['reason'])}</p>")
    parts.append(_img(_rms_figure(report), "RMS per step against the noise level"))
    parts.append(
        f"<p><b>Noise level</b> {_esc(_fmt(report['noise_level']))} {_esc(unit)} from the "
        f"<b>{_esc(report['noise_source'])}</b>: {_esc(report['noise_detail'])}</p>"
    )
    parts.append(
        "<p><b>Final residual against the noise:</b> "
        f"{_esc(report['final_vs_noise']['sentence'])}</p>"
    )
    if (bench := report.get("bench")) is not None:
        parts.append(
            f"<p><b>Bench</b> ({_esc(str(bench['source']))}): "
            f"upper {bench['upper_gear_ratio']:g}:1, "
            f"lower {bench['lower_gear_ratio']:g}:1, {bench['microsteps']} microsteps of "
            f"{bench['step_angle_deg']:g}°; worm periods {bench['worm_period_x_deg']:.6g}° / "
            f"{bench['worm_period_y_deg']:.6g}°</p>"
        )
    return parts


def _chain_table(report: DiscrepancyReport, unit: str) -> str:
    """One row per named effect: its size, the RMS it took away and the test that named it."""
    rows = []
    for i, step in enumerate(report["steps"], 1):
        ev = step["evidence"]
        rows.append(
            [
                str(i),
                step["effect"],
                step["summary"].split(": ", 1)[-1],
                _fmt(step["rms_before"]),
                _fmt(step["rms_after"]),
                f"{ev['test']} {ev['f_stat']:.3g}",
                _p(ev["p_value"]),
                f"{ev['alpha']:.2g}",
                f"{ev['delta_bic']:+.1f}",
            ]
        )
    if not rows:
        return "<p>No effect named: the baseline already describes the data.</p>"
    return _table(
        rows,
        [
            "step",
            "effect",
            "fitted magnitude (± standard uncertainty)",
            f"RMS before [{unit}]",
            f"RMS after [{unit}]",
            "statistic",
            "p",
            "level",
            "ΔBIC",
        ],
    )


def _where_section(report: DiscrepancyReport) -> list[str]:
    """Where the disagreement was before the first step, and what is left after the last."""
    parts = ["<h2>Where they disagree</h2><p>Before the first step (strongest first):</p><ul>"]
    parts += [f"<li>{_esc(where)}</li>" for where in report["where"]]
    parts += [f"<li>{_esc(where)}</li>" for where in report.get("where_largest", [])]
    parts.append("</ul><p>After the last step:</p><ul>")
    parts += [f"<li>{_esc(where)}</li>" for where in report["where_final"]]
    parts.append("</ul>")
    return parts


def _residuals_section(
    report: DiscrepancyReport, result: Result, fam: Family, unit: str
) -> list[str]:
    """The residual figures of every stage of the chain, drawn as the data kind is read."""
    parts = ["<h2>Residuals before and after each step</h2>"]
    titles = [f"baseline {report['baseline']}"] + [
        f"after step {i}: + {step['effect']}" for i, step in enumerate(report["steps"], 1)
    ]
    if isinstance(fam, StageLinear | StageKinematic):
        parts.append(_img(_stage_maps(fam, result.fits, titles, unit), "residual maps"))
    elif isinstance(fam, ScalePoly):
        parts.append(_img(_scale_plots(fam, result.fits, titles, unit), "residual plots"))
    parts.append(_img(_histogram(report, result.final), "final residual histogram"))
    return parts


def _candidate_rows(candidates: list[CandidateScore]) -> list[list[str]]:
    """The candidates one step tried, as table rows (the same for every step and the last)."""
    return [_candidate_row(candidate) for candidate in candidates]


def _candidate_row(candidate: CandidateScore) -> list[str]:
    """One candidate's row: its figures and whether it was significant, or why its refit failed."""
    if "significant" not in candidate:  # the refit failed: no figures, the reason
        return [
            candidate["effect"],
            _fmt(None),
            _fmt(None),
            _p(None),
            _fmt(None),
            candidate["error"],
        ]
    return [
        candidate["effect"],
        _fmt(candidate["rms_after"]),
        _fmt(candidate["f_stat"]),
        _p(candidate["p_value"]),
        _fmt(candidate["delta_bic"]),
        "yes" if candidate["significant"] else "no",
    ]


def _candidates_section(report: DiscrepancyReport, unit: str) -> list[str]:
    """What each step tried (folded), and the last step's candidates, none significant (open)."""
    parts = ["<h2>Candidates at each step</h2>"]
    for i, step in enumerate(report["steps"], 1):
        rows = _candidate_rows(step["evidence"]["candidates"])
        parts.append(
            f"<details><summary>step {i}: {_esc(step['effect'])} chosen</summary>"
            + _table(rows, ["candidate", f"RMS after [{unit}]", *_CANDIDATE_HEAD])
            + "</details>"
        )
    rows = _candidate_rows(report["stop"]["candidates"])
    if rows:
        parts.append(
            "<details open><summary>last step: nothing significant</summary>"
            + _table(rows, ["candidate", f"RMS after [{unit}]", *_CANDIDATE_HEAD])
            + "</details>"
        )
    return parts


def _not_tested_section(report: DiscrepancyReport) -> list[str]:
    """What the workflow did not test and why, its notes, and how significance was judged."""
    parts = ["<h2>Not tested</h2>"]
    if report["skipped"]:
        parts.append(
            "<p>Candidates the data cannot support:</p>"
            + _table(
                [[skip["effect"], skip["reason"]] for skip in report["skipped"]],
                ["effect", "reason"],
            )
        )
    parts.append(
        "<p>Effects the baseline already represents:</p>"
        + _table(
            [[entry["effect"], entry["reason"]] for entry in report["already_in_model"]],
            ["effect", "why"],
        )
    )
    if report["notes"]:
        parts.append("<ul>" + "".join(f"<li>{_esc(n)}</li>" for n in report["notes"]) + "</ul>")
    parts.append(
        "<p style='font-size:80%'>Significance: extra-sum-of-squares test at level "
        f"{report['alpha']:g} per step, Bonferroni-corrected over the candidates of the step, "
        "and a BIC gain. Names of effects are those of docs/models.md §5.</p>"
    )
    return parts


def _provenance_section(report: DiscrepancyReport) -> list[str]:
    """Where the report came from, when it says (nothing otherwise)."""
    if prov := report.get("provenance"):
        from service.io.provenance import provenance_lines

        return [
            "<h2>Provenance</h2><p style='font-size:80%'>"
            + "<br>".join(_esc(line) for line in provenance_lines(prov))
            + "</p>"
        ]
    return []
