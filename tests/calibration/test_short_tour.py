"""The stage tours. The validation points' visiting order: every point once; up to nine points the
shortest order (as trying every order finds it), beyond that within a few per cent of it. Stops on
the way of a tour (an adaptive job's validation points): each where its detour is least, cheaper
than a tour of them after it."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from service.calibration.adaptive_design import on_the_way, short_tour


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


@pytest.mark.parametrize("n", [4, 5, 9])
def test_a_lattice_from_any_corner_is_toured_without_a_detour(n):
    # an adaptive job starts at the spread corner nearest the stage: from each corner the tour
    # moves only to neighbours, (n x n - 1) steps of the lattice's spacing in all
    spacing = 24.0 / (n - 1)
    lattice_points = [
        (-12.0 + i * spacing, -12.0 + j * spacing) for j in range(n) for i in range(n)
    ]
    for corner in [(-12.0, -12.0), (12.0, -12.0), (-12.0, 12.0), (12.0, 12.0)]:
        rest = [point for point in lattice_points if point != corner]
        tour = short_tour(corner, rest)
        assert sorted(tour) == sorted(rest)
        assert travel(corner, tour) == pytest.approx((n * n - 1) * spacing), corner


def test_no_points_and_one_point():
    assert short_tour((0.0, 0.0), []) == []
    assert short_tour((0.0, 0.0), [(1.0, 2.0)]) == [(1.0, 2.0)]


@pytest.mark.parametrize("draw", range(10))
def test_a_stop_on_the_way_goes_where_the_detour_is_least(draw):
    rng = np.random.default_rng()
    tour = [tuple(p) for p in rng.uniform(-12, 12, (12, 2)).round(4)]
    stop = tuple(rng.uniform(-12, 12, 2).round(4))
    start = (0.0, 0.0)
    path = on_the_way(start, tour, [stop])
    # the tour's own order is kept, the stop is marked and visited once
    assert [point for point, extra in path if not extra] == tour
    assert [point for point, extra in path if extra] == [stop]
    # no other place (tried every one) makes the travel shorter
    best = min(travel(start, tour[:i] + [stop] + tour[i:]) for i in range(len(tour) + 1))
    assert travel(start, [point for point, _ in path]) == pytest.approx(best, abs=1e-9)


def test_validation_stops_on_a_grid_tour_cost_less_than_a_tour_of_them_after_it():
    # the adaptive job's 4 x 4 spread over ±12° in serpentine order, and eight stops drawn over the
    # range: on the way they add a few degrees of travel, a tour of them after the grid tens
    grid = [(x, y) for y in (-12, -3, 3, 12) for x in (-12, -3, 3, 12)]
    grid = [p for row in range(4) for p in (grid[4 * row : 4 * row + 4][:: 1 - 2 * (row % 2)])]
    rng = np.random.default_rng()
    for _ in range(20):
        stops = [tuple(p) for p in rng.uniform(-12, 12, (8, 2)).round(4)]
        interleaved = travel((0.0, 0.0), [point for point, _ in on_the_way((0, 0), grid, stops)])
        after = travel((0.0, 0.0), grid + short_tour(grid[-1], stops))
        assert interleaved < after
