"""The validation points' visiting order: every point once; up to nine points the shortest order
(as trying every order finds it), beyond that within a few per cent of it."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from service.calibration.adaptive_design import short_tour


def travel(start, path) -> float:
    stops = [start, *path]
    return sum(max(abs(a[0] - b[0]), abs(a[1] - b[1])) for a, b in zip(stops, stops[1:]))


@pytest.mark.parametrize("draw", range(20))
def test_up_to_nine_points_the_tour_is_the_shortest(draw):
    rng = np.random.default_rng()
    points = [tuple(p) for p in rng.uniform(-12, 12, (7, 2)).round(4)]
    start = (12.0, 12.0)
    tour = short_tour(start, points)
    assert sorted(tour) == sorted(points)
    best = min(travel(start, order) for order in itertools.permutations(points))
    assert travel(start, tour) == pytest.approx(best, abs=1e-9), (travel(start, tour), best)


@pytest.mark.parametrize("draw", range(5))
def test_beyond_nine_points_the_tour_is_much_shorter_than_the_drawn_order(draw):
    rng = np.random.default_rng()
    points = [tuple(p) for p in rng.uniform(-12, 12, (30, 2)).round(4)]
    tour = short_tour((12.0, 12.0), points)
    assert sorted(tour) == sorted(points)
    # 30 random points in a 24° square: the drawn order averages about 12° a move, a good order
    # well under half of that
    assert travel((12.0, 12.0), tour) < 0.5 * travel((12.0, 12.0), points)


def test_no_points_and_one_point():
    assert short_tour((0.0, 0.0), []) == []
    assert short_tour((0.0, 0.0), [(1.0, 2.0)]) == [(1.0, 2.0)]
