"""An adaptive stage calibration's plan: which points, how many readings at each, in what order, to
reach a target expanded uncertainty of the correction in the least bench time. Pure: numbers in, a
plan out.

What a stage record corrects with is the measurement sensor's model against the reference (zero
offsets, scales, yaw, non-orthogonality, seat tilt: MEAS_PARAMS), fitted to the point means.
Linearised about a nominal mounting, a point at table tilt (X, Y) read n times contributes
Σ_axis J_a(X, Y)ᵀJ_a(X, Y)·n/σ_a² to the information matrix (σ_a² = σ_meas,a² + σ_ref,a², one
reading of each on axis a: each axis weighed by its own noise, as the fit weighs it), and the
corrected tilt's variance at (X, Y) from the parameters is g C gᵀ, C the inverse information and g
the same Jacobian (the correction is the model inverted, whose sensitivity to a parameter is minus
the forward one). The criterion is the mean of that variance over the requested range
(I-optimality); the figure checked against the target is the expanded uncertainty of the correction
over the range, k·√(max over the range of the variance + the components every corrected tilt
carries: standards, resolutions), which is the record's part of a corrected tilt's uncertainty (a
live reading's own noise adds to it when the record is used).

The plan starts from a spread grid (min_grid × min_grid of the candidate lattice, so the diagnosis
has points over the whole range to test its candidate effects on), adds candidate points by the
criterion while they save bench time, and reads every point the number of times that brings the
predicted U to the target (the fit weighs point means alike, so equal readings are what its
covariance will show). Points are visited in serpentine order (rows of y, x alternating).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace
from typing import TypedDict

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from service.calibration.methods.stage.common import MEAS_PARAMS, meas_forward

K_EXPANDED = 2.0  # coverage factor of the expanded uncertainty (95 %, many degrees of freedom)
MIN_READINGS = 5
CAP_READINGS = 200  # at most this many readings at one point
MIN_GRID = 4  # the spread grid: min_grid x min_grid points over the range
# the shares of the target a plan may aim at (the fit's own estimate of the noise scatters, and a
# fit above the target costs a top-up pass): the one with the least expected bench time is chosen
PLAN_MARGINS = (0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9)
# readings of the job's first point, whose spread (each sensor's) is the noise a plan starts from
NOISE_READINGS = 20
EVAL_GRID = 13  # the range is evaluated on this lattice per axis


class TargetUnreachable(ValueError):
    """The target is below what this bench can reach over the range: `floor_deg` is the best it
    can."""

    def __init__(self, target_deg: float, floor_deg: float, why: str) -> None:
        super().__init__(
            f"target_expanded_uncertainty_deg {target_deg:g} deg cannot be reached: {why}; the "
            f"best this bench can reach over the range is {floor_deg:.4g} deg"
        )
        self.target_deg, self.floor_deg = target_deg, floor_deg


@dataclass(frozen=True)
class BenchTimes:
    """What a point costs in bench time: moving at the stage's rate, settling, reading at the output
    rate."""

    stage_rates_deg_per_s: tuple[float, float] = (2.8, 2.8)  # each stage's (x, y)
    settle_s: float = 1.5
    output_rate_hz: float = 25.0
    approach_deg: float = 0.1

    def axis_move_s(self, axis: int, delta_deg: float) -> float:
        """One stage's move of `delta_deg`, with its approach from below."""
        return (abs(delta_deg) + 2 * self.approach_deg) / self.stage_rates_deg_per_s[axis]

    def move_s(self, a: tuple[float, float], b: tuple[float, float]) -> float:
        """A move of the table: the two stages move at once, each at its own rate."""
        return max(self.axis_move_s(axis, b[axis] - a[axis]) for axis in (0, 1))

    def point_s(self, n: int) -> float:
        return self.settle_s + n / self.output_rate_hz


@dataclass(frozen=True)
class BenchNoise:
    """One reading's noise of each sensor (σ, deg), and the components every corrected tilt carries
    (u, deg); where the axes' noises are known apart, one reading's variance of meas − ref on each
    axis (x, y; deg²)."""

    meas_sigma_deg: float
    ref_sigma_deg: float
    fixed_u_deg: float = 0.0  # standards and resolutions, combined
    axis_variances_deg2: tuple[float, float] | None = None

    @property
    def sigma2(self) -> float:
        return self.meas_sigma_deg**2 + self.ref_sigma_deg**2

    @property
    def axis_sigma2(self) -> tuple[float, float]:
        """One reading's variance of meas − ref on the x and on the y axis."""
        return self.axis_variances_deg2 or (self.sigma2, self.sigma2)


class AdaptivePlanJSON(TypedDict):
    """An adaptive plan as a record's validation keeps it: the points (table tilts, degrees, in the
    order the job measures them) and readings at each, the predicted, target and floor expanded
    uncertainties (degrees), the expected bench seconds of the fit points and of the validation
    points (on the job's route from where the stage stood) and the criterion (degrees squared), the
    expanded uncertainty aimed at and the probability that the fit then predicts more than the
    target (a top-up pass)."""

    points: list[list[float]]
    readings: list[int]
    predicted_expanded_uncertainty_deg: float
    target_expanded_uncertainty_deg: float
    floor_expanded_uncertainty_deg: float
    expected_bench_seconds: float
    expected_validation_bench_seconds: float
    criterion_mean_variance_deg2: float
    aimed_expanded_uncertainty_deg: float
    top_up_probability: float


@dataclass(frozen=True)
class Stop:
    """One stand of an adaptive job's route: where (table tilt, deg), whether it is a validation
    point, and how many readings it takes."""

    point: tuple[float, float]
    validating: bool
    readings: int


@dataclass
class AdaptivePlan:
    points: list[tuple[float, float]]
    readings: list[int]
    predicted_u_deg: float  # expanded, over the range
    mean_variance_deg2: float  # the criterion
    bench_seconds: float  # expected, fit points only
    target_deg: float
    floor_deg: float  # every candidate at the cap
    notes: list[str] = field(default_factory=list)
    margin: float = 1.0  # the share of the target the plan aims at
    top_up_probability: float = 0.0  # that the fit then predicts more than the target
    times: BenchTimes = field(default_factory=BenchTimes)  # what the bench time was reckoned with
    validation_bench_seconds: float = 0.0  # expected, on the route (`along`)
    route: list[Stop] = field(default_factory=list)  # fit and validation points as measured

    def along(
        self,
        start: tuple[float, float],
        first: tuple[float, float],
        validation_points: list[tuple[float, float]],
        validation_readings: int,
    ) -> AdaptivePlan:
        """The plan on the route a job takes from `start` (where the stage stands): `first` (one
        of the plan's points, the one nearest), the others on a short tour from it, each validation
        point inserted where it lengthens the tour least; the points in that order, and the bench
        time of the fit points and of the validation points along it."""
        readings_at = dict(zip(self.points, self.readings))
        rest = [point for point in self.points if point != first]
        path = on_the_way(first, short_tour(first, rest), validation_points)
        route = [
            Stop(first, False, readings_at[first]),
            *(
                Stop(point, validating, validation_readings if validating else readings_at[point])
                for point, validating in path
            ),
        ]
        fit_s = validation_s = 0.0
        here = start
        for stop in route:
            seconds = self.times.move_s(here, stop.point) + self.times.point_s(stop.readings)
            if stop.validating:
                validation_s += seconds
            else:
                fit_s += seconds
            here = stop.point
        fit = [stop for stop in route if not stop.validating]
        return replace(
            self,
            points=[stop.point for stop in fit],
            readings=[stop.readings for stop in fit],
            bench_seconds=fit_s,
            validation_bench_seconds=validation_s,
            route=route,
        )

    def as_json(self) -> AdaptivePlanJSON:
        return {
            "aimed_expanded_uncertainty_deg": self.margin * self.target_deg,
            "top_up_probability": self.top_up_probability,
            "points": [list(point) for point in self.points],
            "readings": self.readings,
            "predicted_expanded_uncertainty_deg": self.predicted_u_deg,
            "target_expanded_uncertainty_deg": self.target_deg,
            "floor_expanded_uncertainty_deg": self.floor_deg,
            "expected_bench_seconds": self.bench_seconds,
            "expected_validation_bench_seconds": self.validation_bench_seconds,
            "criterion_mean_variance_deg2": self.mean_variance_deg2,
        }


def nearest_point(
    points: list[tuple[float, float]], pose: tuple[float, float] | None
) -> tuple[float, float]:
    """The one of `points` the stage reaches soonest from `pose` (an adaptive job's first point:
    a job that follows another starts near where that one ended, not across the range); the first
    of them while the pose is not known."""
    if pose is None:
        return points[0]
    return min(points, key=lambda point: stage_travel_deg(point, pose))


def jacobian(
    points: NDArray[np.float64], p0: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """(N, 2, P): d(meas x, meas y)/d(MEAS_PARAMS) at table tilts `points` (N, 2), by central
    differences."""
    p0 = np.zeros(len(MEAS_PARAMS)) if p0 is None else p0
    sign = np.ones(2)
    out = np.empty((points.shape[0], 2, p0.size))
    for j, (_, _, scale) in enumerate(MEAS_PARAMS):
        step = 1e-3 * scale
        up, dn = p0.copy(), p0.copy()
        up[j] += step
        dn[j] -= step
        a1, b1 = meas_forward(up, sign, points[:, 0], points[:, 1])
        a0, b0 = meas_forward(dn, sign, points[:, 0], points[:, 1])
        out[:, 0, j] = (a1 - a0) / (2 * step)
        out[:, 1, j] = (b1 - b0) / (2 * step)
    return out


def lattice(
    x_deg: tuple[float, float], y_deg: tuple[float, float], n_x: int, n_y: int
) -> NDArray[np.float64]:
    xs, ys = np.linspace(x_deg[0], x_deg[1], n_x), np.linspace(y_deg[0], y_deg[1], n_y)
    return np.array([(x, y) for y in ys for x in xs], dtype=float)


class Design:
    """The information of chosen points and the correction's predicted variance over the range."""

    def __init__(
        self, candidates: NDArray[np.float64], evaluation: NDArray[np.float64], noise: BenchNoise
    ) -> None:
        self.candidates = candidates
        self.jc = jacobian(candidates)  # (C, 2, P)
        # per reading, each axis weighed by its own noise
        weight = 1.0 / np.asarray(noise.axis_sigma2, dtype=float)
        self.info_c = np.einsum("cap,a,caq->cpq", self.jc, weight, self.jc)
        self.je = jacobian(evaluation)  # (E, 2, P)
        self.noise = noise

    def variances(self, counts: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """(E, 2) predicted variance of the corrected tilt at the evaluation points; None when
        singular."""
        info = np.einsum("c,cpq->pq", counts, self.info_c)
        try:
            cov = np.linalg.inv(info)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(cov)) or np.linalg.cond(info) > 1e14:
            return None
        variance: NDArray[np.float64] = np.einsum("eap,pq,eaq->ea", self.je, cov, self.je)
        return variance

    def criterion(self, counts: NDArray[np.float64]) -> float:
        variance = self.variances(counts)
        return math.inf if variance is None else float(variance.mean())

    def expanded_u(self, counts: NDArray[np.float64]) -> float:
        variance = self.variances(counts)
        if variance is None:
            return math.inf
        return K_EXPANDED * math.sqrt(float(variance.max()) + self.noise.fixed_u_deg**2)


def serpentine(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Rows of equal y in increasing y, x alternating direction: short travel, every point from
    below."""
    rows: dict[float, list[tuple[float, float]]] = {}
    for point in points:
        rows.setdefault(round(point[1], 9), []).append(point)
    out: list[tuple[float, float]] = []
    for i, y in enumerate(sorted(rows)):
        out += sorted(rows[y], reverse=bool(i % 2))
    return out


EXACT_TOUR_POINTS = 9  # up to this many points the shortest order is found exactly (Held-Karp)
TWO_OPT_POINTS = 150  # up to this many the nearest-neighbour order is improved by 2-opt


def short_tour(
    start: tuple[float, float], points: list[tuple[float, float]]
) -> list[tuple[float, float]]:
    """`points` in an order that keeps the stages' travel short, from `start`: the shortest order
    (Held-Karp) for a few points, else nearest neighbour, improved by 2-opt reversals up to
    TWO_OPT_POINTS, or a serpentine through the points where one is shorter (a lattice). Distance
    is the larger of the two axes' moves (the two stages move at once)."""
    stops = np.array([start, *points], dtype=float).reshape(-1, 2)
    n = len(points)
    distances = np.abs(stops[:, None, :] - stops[None, :, :]).max(axis=2)
    if n <= EXACT_TOUR_POINTS:
        return [points[i - 1] for i in _held_karp(distances)]
    order = _nearest_neighbour(distances)
    tour = [points[i - 1] for i in (_two_opt(distances, order) if n <= TWO_OPT_POINTS else order)]
    # on a lattice, nearest neighbour and 2-opt can end a row on the wrong side; a serpentine from
    # the nearest corner cannot
    return min((tour, *_serpentines(points)), key=lambda path: _path_deg(start, path))


def _serpentines(points: list[tuple[float, float]]) -> list[list[tuple[float, float]]]:
    """The points in serpentine order every way there is: rows along either axis, taken from
    either end, the first row run either way (eight orders)."""
    orders = []
    for across in (0, 1):  # rows of equal coordinate `across`, run along the other axis
        rows: dict[float, list[tuple[float, float]]] = {}
        for point in points:
            rows.setdefault(round(point[across], 9), []).append(point)
        for rows_up in (True, False):
            for first_up in (True, False):
                order: list[tuple[float, float]] = []
                for i, key in enumerate(sorted(rows, reverse=not rows_up)):
                    up = first_up if i % 2 == 0 else not first_up
                    order += sorted(rows[key], key=lambda point: point[1 - across], reverse=not up)
                orders.append(order)
    return orders


def _path_deg(start: tuple[float, float], path: list[tuple[float, float]]) -> float:
    """The stages' travel along `path` from `start`."""
    stops = [start, *path]
    return sum(stage_travel_deg(a, b) for a, b in zip(stops, stops[1:]))


def stage_travel_deg(a: tuple[float, float], b: tuple[float, float]) -> float:
    """The travel between two stage points: the larger of the two axes' moves (the two stages move
    at once)."""
    return max(abs(a[0] - b[0]), abs(a[1] - b[1]))


def on_the_way(
    start: tuple[float, float],
    tour: list[tuple[float, float]],
    stops: list[tuple[float, float]],
) -> list[tuple[tuple[float, float], bool]]:
    """`tour` (visited in its order from `start`) with each of `stops` inserted where it lengthens
    the travel least, in visiting order: (point, True for one of `stops`). A grid tour passes near
    most points of its range, so a stop on the way costs a short detour where a tour of the stops
    after it crosses the range again."""
    path: list[tuple[tuple[float, float], bool]] = [(point, False) for point in tour]
    for stop in stops:
        places = [start, *(point for point, _ in path)]
        nexts = [*places[1:], None]  # the last place has nothing after it to rejoin
        costs = [_detour_deg(here, stop, after) for here, after in zip(places, nexts)]
        path.insert(int(np.argmin(costs)), (stop, True))
    return path


def _detour_deg(
    here: tuple[float, float], stop: tuple[float, float], after: tuple[float, float] | None
) -> float:
    """The travel a stop adds between `here` and `after` (at the end of the tour: just getting
    there)."""
    there = stage_travel_deg(here, stop)
    if after is None:
        return there
    return there + stage_travel_deg(stop, after) - stage_travel_deg(here, after)


def _two_opt(d: NDArray[np.float64], order: list[int]) -> list[int]:
    """Reverse stretches of the open path from stop 0 while any reversal shortens it."""
    path = [0, *order]
    improved = True
    while improved:
        improved = False
        for i in range(1, len(path) - 1):
            for j in range(i + 1, len(path)):
                # reversing path[i..j] swaps the edges (i-1, i) and (j, j+1) for (i-1, j) and
                # (i, j+1); an open path's last stop has no edge after it
                has_next = j + 1 < len(path)
                old_tail = d[path[j], path[j + 1]] if has_next else 0.0
                new_tail = d[path[i], path[j + 1]] if has_next else 0.0
                gain = d[path[i - 1], path[i]] + old_tail - d[path[i - 1], path[j]] - new_tail
                if gain > 1e-12:
                    path[i : j + 1] = path[i : j + 1][::-1]
                    improved = True
    return path[1:]


def _nearest_neighbour(d: NDArray[np.float64]) -> list[int]:
    seen = np.zeros(d.shape[0], dtype=bool)
    seen[0] = True
    here, order = 0, []
    for _ in range(d.shape[0] - 1):
        here = int(np.argmin(np.where(seen, np.inf, d[here])))
        seen[here] = True
        order.append(here)
    return order


def _held_karp(d: NDArray[np.float64]) -> list[int]:
    """The shortest open path from stop 0 through every other stop (indices 1..n)."""
    n = d.shape[0] - 1
    if n == 0:
        return []
    # best[(visited set as bits, last stop)] = (length, previous stop)
    best: dict[tuple[int, int], tuple[float, int]] = {
        (1 << (k - 1), k): (float(d[0, k]), 0) for k in range(1, n + 1)
    }
    for size in range(2, n + 1):
        for subset in itertools.combinations(range(1, n + 1), size):
            bits = sum(1 << (k - 1) for k in subset)
            for last in subset:
                rest = bits & ~(1 << (last - 1))
                best[(bits, last)] = min(
                    (best[(rest, prev)][0] + float(d[prev, last]), prev)
                    for prev in subset
                    if prev != last
                )
    bits = (1 << n) - 1
    last = min(range(1, n + 1), key=lambda k: best[(bits, k)][0])
    order = []
    while last != 0:
        order.append(last)
        bits, last = bits & ~(1 << (last - 1)), best[(bits, last)][1]
    return order[::-1]


def spread_indices(n_x: int, n_y: int, min_grid: int) -> list[int]:
    """The candidate lattice's points nearest a min_grid x min_grid grid over the whole range."""
    ix = sorted({int(round(position)) for position in np.linspace(0, n_x - 1, min(min_grid, n_x))})
    iy = sorted({int(round(position)) for position in np.linspace(0, n_y - 1, min(min_grid, n_y))})
    return [j * n_x + i for j in iy for i in ix]


def spread_points(
    x_deg: tuple[float, float], y_deg: tuple[float, float], n_x: int, n_y: int
) -> list[tuple[float, float]]:
    """An adaptive job's spread grid over the candidate lattice n_x x n_y of the range (table tilts,
    deg): its first points, among which it starts."""
    cand = lattice(x_deg, y_deg, n_x, n_y)
    return [(float(cand[i, 0]), float(cand[i, 1])) for i in spread_indices(n_x, n_y, MIN_GRID)]


def floor_u(design: Design) -> float:
    """The best expanded U over the range: every candidate read the cap number of times."""
    return design.expanded_u(np.full(design.candidates.shape[0], float(CAP_READINGS)))


def readings_needed(v_max_one: float, target_deg: float, fixed_u_deg: float) -> float:
    """Readings per point for the parameter part to fit in the target: k²(v/n + u_fixed²) ≤ T²."""
    room = (target_deg / K_EXPANDED) ** 2 - fixed_u_deg**2
    return math.inf if room <= 0 else v_max_one / room


def plan_adaptive(
    x_deg: tuple[float, float],
    y_deg: tuple[float, float],
    n_x: int,
    n_y: int,
    target_deg: float,
    noise: BenchNoise,
    times: BenchTimes = BenchTimes(),
    min_grid: int = MIN_GRID,
    margins: tuple[float, ...] = PLAN_MARGINS,
) -> AdaptivePlan:
    """The adaptive plan over the candidate lattice n_x x n_y of the range; TargetUnreachable when
    even the floor (every candidate at the cap) is above the target, or the fixed components alone
    are.

    The fit weighs every point alike (its point means are fitted unweighted), so every chosen point
    is read the same number of times n: the n at which the point's share of the variance brings the
    predicted U to a margin x the target. Of the `margins`, the plan whose bench time, a top-up
    pass weighed by its probability (`top_up_probability`), is least: a low margin costs readings,
    a high one a likely second pass. Points are added greedily, each time the candidate that
    most lowers the mean predicted variance over the range (the criterion), as long as the n it
    saves at every point is worth more bench time than the point costs (a move, settling, its
    readings); and while n would exceed the cap.
    """
    fixed_floor = K_EXPANDED * noise.fixed_u_deg
    if target_deg <= fixed_floor:
        raise TargetUnreachable(
            target_deg,
            fixed_floor,
            "the standards' and resolutions' part of every corrected tilt "
            f"is already {fixed_floor:.4g} deg (expanded)",
        )
    cand = lattice(x_deg, y_deg, n_x, n_y)
    evaluation = lattice(x_deg, y_deg, EVAL_GRID, EVAL_GRID)
    design = Design(cand, evaluation, noise)
    best = floor_u(design)
    if best > target_deg:
        raise TargetUnreachable(
            target_deg,
            best,
            f"with the bench's reading noise (meas {noise.meas_sigma_deg:.2g}, ref "
            f"{noise.ref_sigma_deg:.2g} deg a reading), every one of the "
            f"{cand.shape[0]} candidate points read {CAP_READINGS} times",
        )
    options = [
        _plan_at(design, cand, margin, (x_deg, y_deg, n_x, n_y, min_grid), target_deg, best, times)
        for margin in margins
    ]
    # a top-up pass reads the plan's points again: about the plan's bench time once more
    return min(options, key=lambda plan: plan.bench_seconds * (1.0 + plan.top_up_probability))


def _plan_at(
    design: Design,
    cand: NDArray[np.float64],
    margin: float,
    grid: tuple[tuple[float, float], tuple[float, float], int, int, int],
    target_deg: float,
    best: float,
    times: BenchTimes,
) -> AdaptivePlan:
    """The plan that aims at `margin` x the target, with the probability of its top-up."""
    x_deg, y_deg, n_x, n_y, min_grid = grid
    noise = design.noise
    chosen = np.zeros(cand.shape[0], dtype=bool)
    chosen[spread_indices(n_x, n_y, min_grid)] = True
    aim = margin * target_deg

    def n_for(mask: NDArray[np.bool_]) -> float:
        variance = design.variances(mask.astype(float))
        return (
            math.inf
            if variance is None
            else max(
                readings_needed(float(variance.max()), aim, noise.fixed_u_deg), float(MIN_READINGS)
            )
        )

    def cost(mask: NDArray[np.bool_], n: float) -> float:
        tour = serpentine([(float(cand[i, 0]), float(cand[i, 1])) for i in np.nonzero(mask)[0]])
        travel = sum(times.move_s(from_pt, to_pt) for from_pt, to_pt in zip(tour, tour[1:]))
        return travel + float(mask.sum()) * times.point_s(int(math.ceil(n)))

    n = n_for(chosen)
    while True:
        here = design.criterion(chosen.astype(float))
        addition = _best_addition(design, chosen)
        if addition is None:
            break
        crit, trial = addition
        n_trial = n_for(trial)
        if crit < here and (n > CAP_READINGS or cost(trial, n_trial) < cost(chosen, n)):
            chosen, n = trial, n_trial
        else:
            break
    n_int = int(min(math.ceil(n), CAP_READINGS))
    idx = np.nonzero(chosen)[0]
    order = serpentine([(float(cand[i, 0]), float(cand[i, 1])) for i in idx])
    counts = chosen.astype(float) * n_int
    predicted = design.expanded_u(counts)
    return AdaptivePlan(
        order,
        [n_int] * len(order),
        predicted,
        design.criterion(counts),
        _tour_seconds((x_deg[0], y_deg[0]), order, n_int, times),
        target_deg,
        best,
        [
            (
                f"{len(order)} points ({min_grid} x {min_grid} spread for the diagnosis, the "
                "rest chosen for the mean predicted variance of the corrected tilt over the "
                f"range), {n_int} readings each, aimed at {margin:g} x the target"
            )
        ],
        margin,
        top_up_probability(predicted / target_deg, len(order)),
        times,
    )


def top_up_probability(share: float, n_points: int, noise_readings: int = NOISE_READINGS) -> float:
    """The probability that a fit of `n_points` points predicts more than the target when the plan
    predicts `share` x it from each axis's noise estimated on `noise_readings` readings of each
    sensor.

    The fit estimates each axis's residual variance on n − p/2 degrees of freedom (p the
    measurement sensor's parameters, service.calibration.methods.stage.chain) and states the larger
    axis's; the plan's noise of each axis has 2 (noise_readings − 1) (two sensors). So the fit's
    prediction over the plan's is √(max over the axes of X_a / D_a), X ~ χ²(a)/a, D ~ χ²(b)/b, all
    four independent: it exceeds 1/share with 1 − E_D[F_a(D a / share²)]²."""
    if share <= 0.0:
        return 0.0
    a = max(n_points - len(MEAS_PARAMS) / 2.0, 1.0)
    b = 2.0 * max(noise_readings - 1, 1)
    q = 1.0 / share**2
    d = np.linspace(1e-6, 6.0, 4001)
    weight = stats.chi2.pdf(d * b, b) * b
    below_one_axis = np.trapezoid(stats.chi2.cdf(q * d * a, a) * weight, d)
    return float(min(max(1.0 - below_one_axis**2, 0.0), 1.0))


def _best_addition(
    design: Design, chosen: NDArray[np.bool_]
) -> tuple[float, NDArray[np.bool_]] | None:
    """The greedy step: (criterion, choice) with the best candidate added; None when all are in."""
    options = []
    for candidate in np.nonzero(~chosen)[0]:
        trial = chosen.copy()
        trial[candidate] = True
        options.append((design.criterion(trial.astype(float)), int(candidate)))
    if not options:
        return None
    crit, pick = min(options)
    trial = chosen.copy()
    trial[pick] = True
    return crit, trial


def _tour_seconds(
    start: tuple[float, float], order: list[tuple[float, float]], readings: int, times: BenchTimes
) -> float:
    """The plan's bench time: each move of the tour from `start`, then settling and the readings."""
    seconds, here_pt = 0.0, start
    for point in order:
        seconds += times.move_s(here_pt, point) + times.point_s(readings)
        here_pt = point
    return seconds


def predicted_u_of_covariance(
    cov: NDArray[np.float64],
    x_deg: tuple[float, float],
    y_deg: tuple[float, float],
    fixed_u_deg: float,
    p0: NDArray[np.float64] | None = None,
) -> float:
    """The expanded U of the correction over the range from a fitted model's covariance of
    MEAS_PARAMS."""
    je = jacobian(lattice(x_deg, y_deg, EVAL_GRID, EVAL_GRID), p0)
    variance = np.einsum("eap,pq,eaq->ea", je, cov, je)
    return K_EXPANDED * math.sqrt(float(variance.max()) + fixed_u_deg**2)
