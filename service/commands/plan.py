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
        "scenario's grid), the readings at each,\nthe expected bench time and the predicted "
        "expanded uncertainty of the correction over the range.\nThe noise, resolutions, stage "
        "speed and settling are the scenario's; nothing is measured.",
        examples=[
            "tiltlab plan --scenario seed000 --target 0.0006",
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
    sc = load_scenario(args.scenario)
    if not isinstance(sc, StageScenario):
        raise InputError(
            f"--scenario {args.scenario}: a {sc.kind} scenario; the adaptive design plans stage "
            "calibrations"
        )
    try:
        plan = plan_for_scenario(sc, args.target)
    except TargetUnreachable as exc:
        raise InputError(str(exc)) from None
    if args.json:
        print(json.dumps(plan.as_json(), indent=2))
        return 0
    print(
        f"target expanded uncertainty {plan.target_deg:g} deg; predicted "
        f"{plan.predicted_u_deg:.4g} deg over the range (best reachable {plan.floor_deg:.3g} deg)"
    )
    print(
        f"{len(plan.points)} points, {plan.readings[0]} readings each; expected bench time "
        f"{plan.bench_seconds:.0f} s (fit points; validation points come on top)"
    )
    print(
        f"aimed at {plan.margin:g} x the target: the fit predicts more than the target, and the "
        f"job reads the points again, with probability {plan.top_up_probability:.2f}"
    )
    print("order  x_deg    y_deg    readings")
    for i, ((x, y), n) in enumerate(zip(plan.points, plan.readings), 1):
        print(f"{i:5d}  {x:7.3f}  {y:7.3f}  {n:8d}")
    return 0
