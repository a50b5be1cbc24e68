"""Coverage of `GET /tilt`'s uncertainty on the path users read, against the simulated world's true
table tilt.

An in-process daemon on a simulated stage bench (sped up, on in-memory lines) calibrates a 5 x 5
grid at ±4° (10 readings per point), activates the record, then stands the stage at random poses
inside that range. At each stand, after the table has settled, it takes distinct single readings of
`/tilt` and one averaged tilt (`average_s` over the readings at rest), each compared with the
world's true tilt of that stand (its positioning error included). The benchmark repeats this over
several calibrations (the averaged tilt's errors at the stands of one calibration share its
parameter error: one calibration is one draw of it); the daemon's coverage test runs one.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import functools
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypedDict, TypeVar

import numpy as np
from fastapi.testclient import TestClient
from numpy.typing import NDArray

from service.api.app import create_app
from service.bench.runtime import BenchRuntime
from service.config import Settings
from service.instruments.base import Reading

GRID = {"x_deg": [-4.0, 4.0], "y_deg": [-4.0, 4.0], "n_x": 5, "n_y": 5}
POSES_WITHIN_DEG = 3.5  # the stands lie inside the calibrated range
# bench seconds after a move: the presets' settling has died out (to well below the noise)
SETTLED_AFTER_S = 3.0


class TableTiltAnswer(TypedDict):
    """The part of `GET /tilt`'s `table_tilt` read here (the API's TableTilt)."""

    x_deg: float
    y_deg: float
    expanded_uncertainty_x_deg: float | None
    expanded_uncertainty_y_deg: float | None
    n_readings: int | None  # with average_s
    window_s: float | None  # with average_s


class TiltAnswer(TypedDict):
    """The part of a `GET /tilt` answer read here (the API's Tilt)."""

    time_utc: str
    stale: bool | None
    table_tilt: TableTiltAnswer | None
    note: str


_Found = TypeVar("_Found")


@dataclass
class StandReadings:
    """Errors (corrected - true) and stated expanded uncertainties, columns x and y: one row per
    distinct single reading, and one row per stand for the averaged tilt."""

    errors: NDArray[np.float64]
    expanded: NDArray[np.float64]
    mean_errors: NDArray[np.float64]
    mean_expanded: NDArray[np.float64]
    mean_readings: NDArray[np.float64]  # how many readings each averaged tilt is of
    # each averaged tilt as served, with the measurement sensor's readings it is the mean of
    averaged: list[tuple[TableTiltAnswer, list[Reading]]] = field(default_factory=list)


def _until(condition: Callable[[], _Found | None], timeout_s: float, what: str) -> _Found:
    """The first truthy value `condition` gives, asked again until `timeout_s` has passed."""
    deadline = time.monotonic() + timeout_s
    while not (value := condition()):
        if time.monotonic() > deadline:
            raise TimeoutError(f"never happened within {timeout_s:g} s: {what}")
        time.sleep(0.005)
    return value


@contextlib.contextmanager
def calibrated_daemon(
    data_dir: Path, scenario: str, sim_speed: float = 20.0
) -> Iterator[tuple[TestClient, dict[str, str]]]:
    """An in-process daemon on `scenario` with an active kinematic record of GRID, and its admin
    headers."""
    with TestClient(
        create_app(
            Settings(
                data_dir=data_dir,
                sim_speed=sim_speed,
                sim_transport="loopback",
                bench_scenario=scenario,
            )
        )
    ) as client:
        headers = {"Authorization": "Bearer " + (data_dir / "admin.token").read_text().strip()}
        calibrate_and_activate(client, headers)
        yield client, headers


def calibrate_and_activate(client: TestClient, h: dict[str, str]) -> None:
    """Calibrate GRID (kinematic, 10 readings per point) and make the record the active one."""
    response = client.post(
        "/calibrations",
        headers=h,
        json={
            "procedure": "stage-grid",
            "method": "kinematic",
            "grid": GRID,
            "samples_per_point": 10,
            "validation": {"n_points": 0},
        },
    )
    if response.status_code != 202:
        raise RuntimeError(f"calibration refused: {response.text}")
    job = _until(
        lambda: (
            (j := client.get(f"/calibrations/{response.json()['id']}", headers=h).json())["state"]
            in ("succeeded", "failed", "cancelled")
            and j
        ),
        600,
        "the calibration's end",
    )
    if job["state"] != "succeeded":
        raise RuntimeError(f"calibration {job['state']}: {job}")
    client.post(f"/records/{job['record']['id']}/activate", headers=h).raise_for_status()


def readings_at_stands(
    client: TestClient, h: dict[str, str], stands: int, readings_per_stand: int, seed: int
) -> StandReadings:
    """Single and averaged readings of /tilt at `stands` random stands, with the world's truth of
    each."""
    bench = client.app.state.bench  # type: ignore[attr-defined]
    world = bench.sim.world
    rng = np.random.default_rng(seed)
    errors, expanded, mean_errors, mean_expanded, counts = [], [], [], [], []
    averaged: list[tuple[TableTiltAnswer, list[Reading]]] = []
    for _ in range(stands):
        pose = rng.uniform(-POSES_WITHIN_DEG, POSES_WITHIN_DEG, 2).round(3)
        client.post(
            "/stage/move", headers=h, json={"x_deg": pose[0], "y_deg": pose[1]}
        ).raise_for_status()
        # from the bench's mark after the move (a lagging reader may still hand out readings made
        # during it) and the settling: the first reading made then, and every /tilt reading stamped
        # from it on
        settled_at = bench.pose.still_since_bench_s + SETTLED_AFTER_S
        first = _until(
            functools.partial(bench.readings_after, "measurement_sensor", settled_at),
            30,
            "a reading of the settled stand",
        )[0]
        seen: set[str] = set()

        def new_reading(seen: set[str] = seen, first: Reading = first) -> TiltAnswer | None:
            t: TiltAnswer = client.get("/tilt", headers=h).json()
            fresh = (
                t["time_utc"] not in seen
                and dt.datetime.fromisoformat(t["time_utc"]) >= first.time_utc
            )
            return t if fresh and not t["stale"] else None

        while len(seen) < readings_per_stand:
            tilt = _until(new_reading, 30, "a new reading on /tilt")
            seen.add(tilt["time_utc"])
            table, truth = tilt["table_tilt"], world.true_tilt_deg()
            if table is None:  # the record is active and the sensor reads: never
                raise RuntimeError(f"a reading on /tilt without a table tilt: {tilt['note']}")
            errors.append([table["x_deg"] - truth[0], table["y_deg"] - truth[1]])
            expanded.append(
                [table["expanded_uncertainty_x_deg"], table["expanded_uncertainty_y_deg"]]
            )
        # the average of the readings at rest; asked again while the latest reading is stale (a
        # sped-up bench on a busy machine can miss a few of its output intervals in real time), for
        # at most 10 s
        answers: list[TiltAnswer] = []

        def average(
            answers: list[TiltAnswer] = answers, settled_at: float = settled_at
        ) -> TableTiltAnswer | None:
            at_rest_s = bench.clock.monotonic() - settled_at  # bench seconds of readings at rest
            answers.append(
                client.get("/tilt", headers=h, params={"average_s": round(at_rest_s, 3)}).json()
            )
            return answers[-1]["table_tilt"]

        try:
            table = _until(average, 10, "an averaged tilt of the readings at rest")
        except TimeoutError:
            raise RuntimeError(f"no averaged tilt at rest: {answers[-1]['note']}") from None
        truth = world.true_tilt_deg()
        averaged.append((table, _window_of(bench, answers[-1], table)))
        mean_errors.append([table["x_deg"] - truth[0], table["y_deg"] - truth[1]])
        mean_expanded.append(
            [table["expanded_uncertainty_x_deg"], table["expanded_uncertainty_y_deg"]]
        )
        counts.append(table["n_readings"])
    return StandReadings(
        np.asarray(errors),
        np.asarray(expanded),
        np.asarray(mean_errors),
        np.asarray(mean_expanded),
        np.asarray(counts, dtype=float),
        averaged,
    )


def _window_of(bench: BenchRuntime, answer: TiltAnswer, table: TableTiltAnswer) -> list[Reading]:
    """The readings an averaged tilt is the mean of: its `n_readings` readings of both axes up to
    the latest, the reading the answer is stamped with."""
    latest_utc = dt.datetime.fromisoformat(answer["time_utc"])
    kept = [
        reading
        for reading in bench.readings_after("measurement_sensor", float("-inf"))
        if reading.x_deg is not None and reading.y_deg is not None
    ]
    ends = [i for i, reading in enumerate(kept) if reading.time_utc == latest_utc]
    if not ends or table["n_readings"] is None:
        raise RuntimeError(f"the averaged tilt's readings are not kept: {answer['time_utc']}")
    return kept[ends[-1] - table["n_readings"] + 1 : ends[-1] + 1]


def measure(
    scenario: str, calibrations: int, stands: int = 60, readings_per_stand: int = 20
) -> Iterator[StandReadings]:
    """`readings_at_stands` after each of `calibrations` calibrations, each daemon in a fresh data
    directory, yielded as each is done."""
    for k in range(calibrations):
        with (
            tempfile.TemporaryDirectory(prefix="tiltlab-coverage-") as tmp,
            calibrated_daemon(Path(tmp), scenario) as (client, headers),
        ):
            yield readings_at_stands(
                client, headers, stands, readings_per_stand, seed=1000 * k + len(scenario)
            )
