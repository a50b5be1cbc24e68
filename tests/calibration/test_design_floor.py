"""The adaptive design's floor on a bench: its parts add up from the route, with no settling where
the scenario has none, and settling as the physics says where it has."""

from __future__ import annotations

import pytest

from service.calibration.adaptive_design import nearest_point, spread_points
from service.physics.settling import settling_of
from service.scenarios.model import load_scenario, parse_scenario
from service.scenarios.plan import design_floor, plan_for_scenario
from service.scenarios.run import effect_set


def _without_settling():
    data = load_scenario("seed000").model_dump(mode="json")
    data["effects"].pop("settling", None)
    return parse_scenario(data)


def test_without_settling_the_floor_is_the_route_moved_and_read():
    sc = _without_settling()
    assert settling_of(effect_set(sc)).is_instant
    floor = design_floor(sc, 0.0005, 8, 10)
    first = nearest_point(spread_points((-12, 12), (-12, 12), 9, 9), (0.0, 0.0))
    plan = plan_for_scenario(sc, 0.0005, first, 8, 10, (1.0,))
    stops = [first, *(stop.point for stop in plan.route)]
    moved = sum(plan.times.move_s(a, b) for a, b in zip(stops, stops[1:]) if a != b)
    assert floor.settling == 0.0
    assert floor.moving == pytest.approx(moved)
    assert floor.reading == pytest.approx(
        sum(stop.readings for stop in plan.route) / plan.times.output_rate_hz
    )
    assert floor.total == pytest.approx(floor.moving + floor.reading)


def test_a_slower_sensor_raises_only_the_floor_s_settling():
    fast = load_scenario("seed000")
    data = fast.model_dump(mode="json")
    data["effects"]["settling"]["sensor_time_constant_s"] = 1.5
    slow = parse_scenario(data)
    a, b = design_floor(fast, 0.0005, 8, 10), design_floor(slow, 0.0005, 8, 10)
    assert a.moving == pytest.approx(b.moving) and a.reading == pytest.approx(b.reading)
    # 24 stands, each some 2 s against 12 s: the lag of a 2 deg/s ramp, rate x tau, decaying
    # to the noise (0.3 ln(600) = 1.9 s, 1.5 ln(3000) = 12.0 s)
    assert 20 * 1.5 < a.settling < 24 * 2.1
    assert 20 * 11 < b.settling < 24 * 12.1


def test_keeping_the_transient_out_of_the_means_raises_a_slow_sensor_s_floor_most():
    """A floor whose point means carry at most half their standard error of the transient settles
    longer than one settled to a reading's noise: on the 0.3 s sensor by a fraction of a second a
    stand (the remnant decays within the first readings), on a 1.5 s one by seconds a stand (it
    decays over them). Moving and reading are the same route's."""
    fast = load_scenario("seed000")
    data = fast.model_dump(mode="json")
    data["effects"]["settling"]["sensor_time_constant_s"] = 1.5
    slow = parse_scenario(data)
    for sc, per_stand_s in ((fast, (0.05, 1.0)), (slow, (1.5, 5.0))):
        loose, kept_out = design_floor(sc, 0.0005, 8, 10), design_floor(sc, 0.0005, 8, 10, 0.5)
        assert kept_out.moving == pytest.approx(loose.moving)
        assert kept_out.reading == pytest.approx(loose.reading)
        stands = 24
        assert (
            loose.settling + stands * per_stand_s[0]
            < kept_out.settling
            < loose.settling + stands * per_stand_s[1]
        )
