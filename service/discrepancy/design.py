"""The designed measurement: the shortest one that tests what a record's stored points cannot.

A diagnosis of stored points can only test what the points exercise. Hysteresis (backlash) needs
points approached from both sides, and a stage-grid job approaches every point from below; a worm's
periodic error needs the stage moved in steps finer than the worm's period, and a grid whose step is
a whole or half number of periods samples it at one or two phases; a drift in time is told from the
bench's geometry only by poses measured again later; a temperature effect needs a temperature span,
which a bench without a climate cannot set. For each candidate the points cannot test (or test too
weakly, or whose named effect the record could not adopt) this plans the few points that would, in
the lab's words, with their approach directions and the bench time they take.

Pure computation: the daemon runs the plan as a job (service.jobs.diagnosis_measurement).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TypedDict

import numpy as np

from service.discrepancy.report_types import DiscrepancyReport, EffectReason
from service.discrepancy.stage_data import StageData
from service.physics.stage import StageBench

if TYPE_CHECKING:
    from service.discrepancy.adopt import AdoptionVerdict

# a worm scan: one period in steps of an eighth (nine points, the last a turn after the first)
EIGHTHS = 9
# a planned point leaves room to be approached from either side (the job's approach)
APPROACH_MARGIN_DEG = 0.1
WIDE_FRACTION = 0.8  # a wider range of tilts for a non-linearity: this much of the stages' travel


@dataclass(frozen=True)
class PlannedPoint:
    """One point of the designed measurement: where the stages go and from which side they arrive
    (+1 from below, -1 from above, per stage)."""

    stage_x_deg: float
    stage_y_deg: float
    dir_x: float
    dir_y: float

    def as_list(self) -> list[float]:
        return [self.stage_x_deg, self.stage_y_deg, self.dir_x, self.dir_y]


@dataclass
class PlanPart:
    """What one candidate needs: why the stored points cannot test it, the measurement, its
    points."""

    effect: str
    why: str
    measurement: str
    points: list[PlannedPoint] = field(default_factory=list)


@dataclass
class Need:
    """A candidate the stored points cannot test (or test too weakly): the reason, and for a worm
    the stages."""

    effect: str
    why: str
    axes: tuple[str, ...] = ()


class PlannedPointJSON(TypedDict):
    """A planned point as the plan lists it (approach +1 from below, -1 from above)."""

    stage_x_deg: float
    stage_y_deg: float
    dir_x: float
    dir_y: float


class PlanPartJSON(TypedDict):
    """One candidate's part of the plan; its points as [stage_x_deg, stage_y_deg, dir_x, dir_y]."""

    effect: str
    why: str
    measurement: str
    n_points: int
    points: list[list[float]]


class MeasurementPlanJSON(TypedDict):
    """The designed measurement as a diagnosis stores and shows it (`MeasurementPlan.as_dict`)."""

    n_points: int
    points: list[PlannedPointJSON]
    parts: list[PlanPartJSON]
    cannot: list[EffectReason]  # what this bench cannot measure, and why
    estimated_bench_s: float
    seconds_per_point: float
    estimate_source: str
    approach: str
    summary: str


@dataclass
class MeasurementPlan:
    parts: list[PlanPart]
    cannot: list[EffectReason]
    seconds_per_point: float
    estimate_source: str

    @property
    def points(self) -> list[PlannedPoint]:
        return [point for part in self.parts for point in part.points]

    @property
    def estimated_bench_s(self) -> float:
        return len(self.points) * self.seconds_per_point

    def as_dict(self) -> MeasurementPlanJSON:
        pts = self.points
        if pts:
            summary = (
                f"{len(pts)} points, about {self.estimated_bench_s / 60:.1f} min of bench time: "
                + "; ".join(
                    f"{part.effect}: {part.measurement} ({len(part.points)} points)"
                    for part in self.parts
                    if part.points
                )
            )
        else:
            summary = "nothing to measure: the stored points test every candidate the bench can"
        if self.cannot:
            summary += "; cannot be measured here: " + ", ".join(
                entry["effect"] for entry in self.cannot
            )
        return {
            "n_points": len(pts),
            "points": [
                {
                    "stage_x_deg": point.stage_x_deg,
                    "stage_y_deg": point.stage_y_deg,
                    "dir_x": point.dir_x,
                    "dir_y": point.dir_y,
                }
                for point in pts
            ],
            "parts": [
                {
                    "effect": part.effect,
                    "why": part.why,
                    "measurement": part.measurement,
                    "n_points": len(part.points),
                    "points": [point.as_list() for point in part.points],
                }
                for part in self.parts
            ],
            "cannot": list(self.cannot),
            "estimated_bench_s": self.estimated_bench_s,
            "seconds_per_point": self.seconds_per_point,
            "estimate_source": self.estimate_source,
            "approach": "+1: the stage arrives from below (moving up), -1: from above, by "
            f"{APPROACH_MARGIN_DEG:g} deg",
            "summary": summary,
        }


def _q(bench: StageBench, x: float, y: float) -> tuple[float, float]:
    """A point as the controller executes it (whole pulses), rounded as commands are written."""
    qx, qy = bench.quantise(x, y)
    return round(float(qx), 6), round(float(qy), 6)


def _inside(v: float, travel: float) -> float:
    lim = travel - APPROACH_MARGIN_DEG
    return float(min(max(v, -lim), lim))


def _poses(data: StageData, n: int = 5) -> list[tuple[float, float]]:
    """A few of the record's own poses spread over its range: the one nearest the centre and those
    nearest the middles of the four quadrants."""
    x, y = data.cmd_x_deg, data.cmd_y_deg
    cx, cy = float(np.median(x)), float(np.median(y))
    hx, hy = float(np.ptp(x)) / 4, float(np.ptp(y)) / 4
    aims = [
        (cx, cy),
        (cx - hx, cy - hy),
        (cx + hx, cy + hy),
        (cx - hx, cy + hy),
        (cx + hx, cy - hy),
    ][:n]
    out: list[tuple[float, float]] = []
    for ax, ay in aims:
        dist = np.hypot(x - ax, y - ay)
        for i in np.argsort(dist):
            pose = (float(x[i]), float(y[i]))
            if pose not in out:
                out.append(pose)
                break
    return out


def _backlash(data: StageData, bench: StageBench, travel: float) -> list[PlannedPoint]:
    pts = []
    for x, y in _poses(data):
        x, y = _q(bench, _inside(x, travel), _inside(y, travel))
        pts += [PlannedPoint(x, y, -1.0, -1.0), PlannedPoint(x, y, 1.0, 1.0)]
    return pts


def _worm_scan(data: StageData, bench: StageBench, axis: str, travel: float) -> list[PlannedPoint]:
    """One worm period of `axis` in eighths, at the record's middle position of the other stage (the
    worm's error is the same wherever the other stage stands; the record's own points give the
    stage's scale)."""
    period = bench.worm_period_x_deg if axis == "x" else bench.worm_period_y_deg
    along = data.cmd_x_deg if axis == "x" else data.cmd_y_deg
    across = data.cmd_y_deg if axis == "x" else data.cmd_x_deg
    start = float(along[np.argmin(np.abs(along - np.median(along)))])
    start = _inside(start, travel)
    if start + period > travel - APPROACH_MARGIN_DEG:
        start = travel - APPROACH_MARGIN_DEG - period
    other = _inside(float(across[np.argmin(np.abs(across - np.median(across)))]), travel)
    pts = []
    for k in range(EIGHTHS):
        position = start + k * period / 8
        x, y = (position, other) if axis == "x" else (other, position)
        x, y = _q(bench, x, y)
        pts.append(PlannedPoint(x, y, 1.0, 1.0))
    return pts


def _wide(data: StageData, bench: StageBench, travel: float) -> list[PlannedPoint]:
    lim = _inside(WIDE_FRACTION * travel, travel)
    pts = []
    for x, y in (
        (-lim, -lim),
        (lim, -lim),
        (lim, lim),
        (-lim, lim),
        (0.0, -lim),
        (lim, 0.0),
        (0.0, lim),
        (-lim, 0.0),
    ):
        x, y = _q(bench, x, y)
        pts.append(PlannedPoint(x, y, 1.0, 1.0))
    return pts


# what a planner adds: parts of the measurement, and needs it cannot meet on this bench
_PlanResult = tuple[list[PlanPart], list[EffectReason]]


def _plan_backlash(
    data: StageData, bench: StageBench, travel_deg: float, need: Need, parts: list[PlanPart]
) -> _PlanResult:
    """Hysteresis: a few record poses approached from both sides."""
    return [
        PlanPart(
            "backlash",
            need.why,
            "five of the record's poses, each approached from above and again "
            "from below: lost motion is the difference",
            _backlash(data, bench, travel_deg),
        )
    ], []


def _plan_worm(
    data: StageData, bench: StageBench, travel_deg: float, need: Need, parts: list[PlanPart]
) -> _PlanResult:
    """A worm's periodic error: one scan in eighths of a period per stage it is needed on."""
    worm_parts = []
    for ax in need.axes or ("x", "y"):
        period = bench.worm_period_x_deg if ax == "x" else bench.worm_period_y_deg
        worm_parts.append(
            PlanPart(
                "periodic_error",
                need.why,
                f"a scan of the {ax} stage over one worm period ({period:.6g} deg) in "
                "eighths, at the middle of the other stage's range",
                _worm_scan(data, bench, ax, travel_deg),
            )
        )
    return worm_parts, []


def _plan_time_drift(
    data: StageData, bench: StageBench, travel_deg: float, need: Need, parts: list[PlanPart]
) -> _PlanResult:
    """A drift in time: record poses measured again later (the backlash part's serve, if
    planned)."""
    if any(part.effect == "backlash" for part in parts):
        return [
            PlanPart(
                "time_drift",
                need.why,
                "the backlash part's points approached from below are record "
                "poses measured again later: they test it too (no further points)",
            )
        ], []
    pts = [
        PlannedPoint(*_q(bench, _inside(x, travel_deg), _inside(y, travel_deg)), 1.0, 1.0)
        for x, y in reversed(_poses(data))
    ]
    return [
        PlanPart(
            "time_drift",
            need.why,
            "five of the record's poses measured again now, in another "
            "order: a drift moves them, the geometry does not",
            pts,
        )
    ], []


def _plan_wide_range(
    data: StageData, bench: StageBench, travel_deg: float, need: Need, parts: list[PlanPart]
) -> _PlanResult:
    """A non-linearity: points over a wider range of tilts, if the travel leaves one."""
    span = float(max(np.max(np.abs(data.cmd_x_deg)), np.max(np.abs(data.cmd_y_deg))))
    if span < WIDE_FRACTION * travel_deg - 0.5:
        return [
            PlanPart(
                "sensor_nonlinearity",
                need.why,
                f"eight points at ±{WIDE_FRACTION * travel_deg:.3g} deg "
                f"(the record spans ±{span:.3g} deg of the ±{travel_deg:g} deg travel)",
                _wide(data, bench, travel_deg),
            )
        ], []
    return [], [
        {
            "effect": "sensor_nonlinearity",
            "reason": f"{need.why}; the record's points already span the "
            "stages' travel: no wider range can be measured on this bench",
        }
    ]


def _plan_temperature(
    data: StageData, bench: StageBench, travel_deg: float, need: Need, parts: list[PlanPart]
) -> _PlanResult:
    """A temperature effect: never measurable here (the bench cannot set its temperature)."""
    span = 0.0 if data.temp_c is None else float(np.ptp(data.temp_c))
    at = "" if data.temp_c is None else f" at {float(np.mean(data.temp_c)):.1f} °C"
    return [], [
        {
            "effect": "temperature_drift",
            "reason": f"{need.why}; the points span {span:.2g} K{at} and this bench cannot set "
            "its temperature: repeat the calibration when the room's temperature differs by "
            "a few kelvin, or on a bench in a climate chamber",
        }
    ]


# in this order: the time-drift part reuses the backlash part's points when there is one
_PLANNERS: dict[
    str, Callable[[StageData, StageBench, float, Need, list[PlanPart]], _PlanResult]
] = {
    "backlash": _plan_backlash,
    "periodic_error": _plan_worm,
    "time_drift": _plan_time_drift,
    "sensor_nonlinearity": _plan_wide_range,
    "temperature_drift": _plan_temperature,
}


def _merged_needs(needs: Sequence[Need]) -> dict[str, Need]:
    """One need per effect: the first reason, and the stages of every need for it together."""
    by_effect: dict[str, Need] = {}
    for need in needs:
        if need.effect in by_effect:
            was = by_effect[need.effect]
            by_effect[need.effect] = Need(
                need.effect, was.why, tuple(sorted(set(was.axes) | set(need.axes)))
            )
        else:
            by_effect[need.effect] = need
    return by_effect


def plan_measurement(
    data: StageData,
    bench: StageBench,
    travel_deg: float,
    needs: Sequence[Need],
    seconds_per_point: float,
    estimate_source: str,
) -> MeasurementPlan:
    """The shortest measurement that tests every need: one part per candidate (a part another part's
    points already serve adds none)."""
    parts: list[PlanPart] = []
    cannot: list[EffectReason] = []
    by_effect = _merged_needs(needs)
    for effect, planner in _PLANNERS.items():
        if (need := by_effect.get(effect)) is not None:
            new_parts, new_cannot = planner(data, bench, travel_deg, need, parts)
            parts += new_parts
            cannot += new_cannot
    for effect, need in by_effect.items():
        if effect not in _PLANNERS:
            cannot.append(
                {
                    "effect": effect,
                    "reason": f"{need.why}; no measurement on this bench is planned for it",
                }
            )
    return MeasurementPlan(parts, cannot, seconds_per_point, estimate_source)


def needs_of(
    report: DiscrepancyReport,
    active: Mapping[str, Sequence[str]],
    adoption: Sequence[AdoptionVerdict],
    weak: float,
    data: StageData | None = None,
) -> list[Need]:
    """What the stored points cannot test, from a diagnosis of them: candidates skipped (with the
    reason), a worm whose sine or cosine the points do not separate on a stage, candidates only
    weakly visible (separability below `weak`), a drift in time when no pose was measured twice, and
    named effects the record cannot adopt from these points."""
    needs: list[Need] = []
    if data is not None and _one_pass_without_drift(report, data):
        needs.append(
            Need(
                "time_drift",
                "every pose was measured once, in one pass: a drift in time is told from "
                "the bench's geometry only as far as the order of the points differs from "
                "their place on the grid",
            )
        )
    needs += _skipped_needs(report)
    worm = active.get("periodic_error")
    if worm is not None and not any(n.effect == "periodic_error" for n in needs):
        needs += _worm_phase_needs(worm)
    needs += _weak_needs(report, weak)
    needs += _unadoptable_needs(adoption)
    return needs


def _one_pass_without_drift(report: DiscrepancyReport, data: StageData) -> bool:
    """Timed points, no pose measured twice, and no drift named: the drift was barely testable."""
    if data.t_s is None or "time_drift" in report.get("named_effects", []):
        return False
    poses = np.round(np.column_stack([data.cmd_x_deg, data.cmd_y_deg]), 6)
    return bool(np.unique(poses, axis=0).shape[0] == len(poses))


def _skipped_needs(report: DiscrepancyReport) -> list[Need]:
    """The candidates the diagnosis skipped as untestable, with its reason."""
    needs = []
    for skip in report.get("skipped", []):
        effect = str(skip["effect"])
        needs.append(
            Need(
                effect,
                f"untestable on the stored points: {skip['reason']}",
                ("x", "y") if effect == "periodic_error" else (),
            )
        )
    return needs


def _worm_phase_needs(worm: Sequence[str]) -> list[Need]:
    """The stages whose worm sine or cosine the diagnosis had to leave out (too few phases)."""
    short = tuple(ax for ax in ("x", "y") if not {f"{ax}_sin_deg", f"{ax}_cos_deg"} <= set(worm))
    if not short:
        return []
    return [
        Need(
            "periodic_error",
            "the stored points sample the worm of the "
            f"{' and '.join(short)} stage at too few phases to tell its periodic error",
            short,
        )
    ]


def _weak_needs(report: DiscrepancyReport, weak: float) -> list[Need]:
    """The remaining candidates the final model sees less than `weak` of."""
    needs = []
    for effect, fracs in (report.get("separability") or {}).items():
        low = {lab: frac for lab, frac in fracs.items() if frac < weak}
        if not low:
            continue
        axes = tuple(sorted({lab[:1] for lab in low})) if effect == "periodic_error" else ()
        worst = min(low.values())
        needs.append(
            Need(
                effect,
                f"only {100 * worst:.0f} % visible on the stored points (the rest of its "
                "signature is a change of what the model already fits)",
                axes,
            )
        )
    return needs


def _unadoptable_needs(adoption: Sequence[AdoptionVerdict]) -> list[Need]:
    """The named effects the record cannot adopt and a measurement would determine."""
    needs = []
    for verdict in adoption:
        if not verdict.get("adoptable") and verdict.get("measurement"):
            effect = str(verdict["effect"])
            axes = (
                tuple(
                    ax for ax in ("x", "y") if f"the {ax} stage" in str(verdict.get("reason", ""))
                )
                if effect == "periodic_error"
                else ()
            )
            needs.append(
                Need(
                    effect,
                    "named, but the record cannot adopt it from the stored points: "
                    f"{verdict['reason']}",
                    axes,
                )
            )
    return needs
