"""`tiltlab plan`: the adaptive calibration plan for a bench description and a target, without a
bench."""

from __future__ import annotations

import argparse
import json

from service.commands._args import add_command, finite
from service.errors import InputError


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = add_command(
        sub,
        "plan",
        "print the adaptive calibration plan for a bench description and a target U",
        description="The plan an adaptive stage calibration (POST /calibrations with design "
        "adaptive) would follow on the\nbench a stage scenario describes: its points (over the "
        "scenario's grid), the readings at each,\nthe route the job takes (from the spread point "
        "nearest where the stage stands, the validation\npoints on the way), the expected bench "
        "time and the predicted expanded uncertainty of the\ncorrection over the range. The "
        "noise, resolutions, stage speed and settling are the scenario's;\nnothing is measured.",
        examples=[
            "tiltlab plan --scenario seed000 --target 0.0006",
            "tiltlab plan --scenario seed000 --target 0.0004 --from 12 12 --validation-points 8",
            "tiltlab plan --scenario my-bench.json --target 0.001 --json",
        ],
    )
    parser.add_argument(
        "--scenario",
        metavar="NAME_OR_FILE",
        required=True,
        help="a stage preset (tiltlab simulate --list) or a stage scenario JSON file",
    )
    parser.add_argument(
        "--target",
        metavar="U_DEG",
        type=finite("the target expanded uncertainty in degrees"),
        required=True,
        help="the target expanded uncertainty (k = 2) of the correction over the range, deg",
    )
    parser.add_argument(
        "--from",
        dest="start",
        metavar=("X_DEG", "Y_DEG"),
        nargs=2,
        type=finite("a stage position in degrees"),
        default=[0.0, 0.0],
        help="where the stage stands when the job starts (table tilt, deg): the job begins at the "
        "spread point nearest it",
    )
    parser.add_argument(
        "--validation-points",
        metavar="N",
        type=int,
        default=4,
        help="validation points the job measures on its way, as the request's validation.n_points",
    )
    parser.add_argument(
        "--samples-per-point",
        metavar="N",
        type=int,
        default=10,
        help="readings of each validation point, as the request's samples_per_point",
    )
    parser.add_argument("--json", action="store_true", help="print the plan as JSON")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from service.calibration.adaptive_design import TargetUnreachable
    from service.scenarios.model import StageScenario, load_scenario
    from service.scenarios.plan import plan_for_scenario

    if not 0 < args.target <= 1:
        raise InputError(
            f"--target {args.target:g}: a target expanded uncertainty is more than 0 and at most 1 "
            "deg"
        )
    if not 0 <= args.validation_points <= 1000:
        raise InputError(
            f"--validation-points {args.validation_points}: from 0 to 1000, as a request's "
            "validation.n_points"
        )
    if not 1 <= args.samples_per_point <= 10_000:
        raise InputError(
            f"--samples-per-point {args.samples_per_point}: from 1 to 10000, as a request's "
            "samples_per_point"
        )
    sc = load_scenario(args.scenario)
    if not isinstance(sc, StageScenario):
        raise InputError(
            f"--scenario {args.scenario}: a {sc.kind} scenario; the adaptive design plans stage "
            "calibrations"
        )
    try:
        plan = plan_for_scenario(
            sc,
            args.target,
            (args.start[0], args.start[1]),
            args.validation_points,
            args.samples_per_point,
        )
    except TargetUnreachable as exc:
        raise InputError(str(exc)) from None
    if args.json:
        route = [
            {
                "x_deg": stop.point[0],
                "y_deg": stop.point[1],
                "validation": stop.validating,
                "readings": stop.readings,
            }
            for stop in plan.route
        ]
        print(json.dumps({**plan.as_json(), "route": route}, indent=2))
        return 0
    print(
        f"target expanded uncertainty {plan.target_deg:g} deg; predicted "
        f"{plan.predicted_u_deg:.4g} deg over the range (best reachable {plan.floor_deg:.3g} deg)"
    )
    n_validation = sum(stop.validating for stop in plan.route)
    print(
        f"{len(plan.points)} points, {plan.readings[0]} readings each, and {n_validation} "
        f"validation points on the way; expected bench time "
        f"{plan.bench_seconds + plan.validation_bench_seconds:.0f} s from ({args.start[0]:g}, "
        f"{args.start[1]:g}) deg ({plan.bench_seconds:.0f} s the fit points, "
        f"{plan.validation_bench_seconds:.0f} s the validation points)"
    )
    print(
        f"aimed at {plan.margin:g} x the target: the fit predicts more than the target, and the "
        f"job reads the points again, with probability {plan.top_up_probability:.2f}"
    )
    print("order  x_deg    y_deg    readings")
    for i, stop in enumerate(plan.route, 1):
        kind = "  validation" if stop.validating else ""
        print(f"{i:5d}  {stop.point[0]:7.3f}  {stop.point[1]:7.3f}  {stop.readings:8d}{kind}")
    return 0
