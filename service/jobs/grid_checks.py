"""What a stage grid must offer its fit, checked when the request comes (422), never after the bench
moved.

A fit refuses points that do not determine its model: every stage must stand at two or more
angles, the method needs enough distinct points, and some models need points off the axes or a
spread the noise cannot hide. The plain preconditions are checked first, each naming the field
at fault; then the fit itself is rehearsed on the planned points with the readings a perfect
bench of the same hardware would give, so a grid whose geometry the fit cannot use is refused
with the fit's own words before a single point is measured.
"""

from __future__ import annotations

import numpy as np

from service.calibration.registry import FitOptions, get_method
from service.errors import DegenerateDataError, FitError
from service.jobs.requests import MIN_POINTS, Grid, RequestProblem
from service.physics.effects import EffectSet
from service.physics.stage import StageBench, offaxis_error_deg, simulate_stage

StagePoint = tuple[float, float]
DISTINCT_DECIMALS = 6  # points closer than a micro-degree are one point (as the fits count them)
AXIS_NAMES = {"x": ("upper", "n_x"), "y": ("lower", "n_y")}


def distinct_points(points: list[StagePoint]) -> int:
    return len({(round(x, DISTINCT_DECIMALS), round(y, DISTINCT_DECIMALS)) for x, y in points})


def check_axis_positions(grid: Grid, points: list[StagePoint]) -> None:
    """Each stage at two or more angles: a fit relates the sensors to both stages' motion."""
    for index, axis in enumerate(("x", "y")):
        stage, count_name = AXIS_NAMES[axis]
        angles = {round(point[index], DISTINCT_DECIMALS) for point in points}
        if len(angles) >= 2:
            continue
        at = f"{next(iter(angles)):g} deg" if angles else "no angle"
        if grid.points is not None:
            raise RequestProblem(
                "grid.points",
                f"every point has the {stage} stage ({axis}) at {at}; the fit needs "
                f"points with the {stage} stage at two or more angles",
            )
        span = grid.x_deg if axis == "x" else grid.y_deg
        count = grid.n_x if axis == "x" else grid.n_y
        if count is not None and count < 2:
            raise RequestProblem(
                f"grid.{count_name}",
                f"{count} {axis} position: the fit needs the {stage} stage at two"
                f" or more angles (give {count_name} of 2 or more)",
            )
        raise RequestProblem(
            f"grid.{axis}_deg",
            f"{span} is an empty range: its {count} points all stand at {at}; give"
            f" two different ends so that the {stage} stage moves",
        )


def check_enough_points(method: str, points: list[StagePoint]) -> None:
    need = MIN_POINTS.get(method, 6)
    have = distinct_points(points)
    if have < need:
        repeated = f" ({len(points) - have} repeated)" if have < len(points) else ""
        raise RequestProblem(
            "grid", f"{have} distinct points{repeated}; the {method} fit needs at least {need}"
        )


def check_off_axis(method: str, points: list[StagePoint]) -> None:
    """The coupling model is seen only where both stages are tilted (its error is zero on the
    axes)."""
    if method != "coupling":
        return
    xs, ys = np.array(points, dtype=float).T
    error = offaxis_error_deg(xs, ys)
    if float(error @ error) < 1e-12:
        raise RequestProblem(
            "grid",
            "every point lies on the x = 0 or y = 0 line (or too close to it); the coupling"
            " fit needs points with both stages tilted, where the off-axis coupling shows",
        )


def rehearse_fit(
    method: str, points: list[StagePoint], hardware: StageBench, options: FitOptions
) -> None:
    """The method's fit on the readings a perfect bench of this hardware gives at the planned
    points.

    A grid whose geometry the fit cannot use fails here as it would after the measurement; the
    message is the fit's own. Real readings differ from these by the instruments' errors and
    noise, which only a measurement can show.
    """
    xs, ys = np.array(points, dtype=float).T
    ideal = simulate_stage(hardware, EffectSet.from_mapping("stage", {}), xs, ys)
    columns = {
        "stage_x_deg": xs,
        "stage_y_deg": ys,
        "dir_x": np.ones_like(xs),
        "dir_y": np.ones_like(xs),
        **{name: ideal[name] for name in ("ref_x_deg", "ref_y_deg", "meas_x_deg", "meas_y_deg")},
    }
    try:
        # noiseless readings: zero residuals divide
        with np.errstate(divide="ignore", invalid="ignore"):
            get_method("stage", method).fit(columns, options)
    except (DegenerateDataError, FitError) as exc:
        raise RequestProblem(
            "grid",
            f"the {method} fit cannot use these points (tried on the readings of a perfect"
            f" bench before measuring): {exc}",
        ) from None


def check_stage_grid(
    method: str, grid: Grid, points: list[StagePoint], hardware: StageBench, options: FitOptions
) -> None:
    """Every precondition of the stage fit, the cheap ones first; RequestProblem names the field."""
    check_axis_positions(grid, points)
    check_enough_points(method, points)
    check_off_axis(method, points)
    rehearse_fit(method, points, hardware, options)
