"""The simulated sensors compute their readings at rest in batches: what the firmware sends is
still the scenario's physics at the present pose, with its noise, and a move is seen at once."""

from __future__ import annotations

import numpy as np

from service.clock import Clock
from service.instruments import controller as ctl
from service.instruments.sim.world import READINGS_PER_BATCH, StageWorld, stage_scenario
from tests.helpers.waiting import eventually


def _world() -> StageWorld:
    world = StageWorld(stage_scenario("seed000"), Clock(1000.0))
    for axis in world.axes.values():
        axis.homed = True
    return world


def _move(world: StageWorld, axis: int, target_pulses: int) -> None:
    assert world.axes[axis].move_to(target_pulses) == ctl.ERR_NONE
    eventually(
        lambda: world.axes[axis].state == ctl.STATE_READY,
        timeout_s=30,
        what="the simulated move ended",
    )


def test_batched_readings_scatter_like_single_samples_about_the_pose() -> None:
    world = _world()
    n = 10 * READINGS_PER_BATCH
    for prefix in ("ref", "meas"):
        batched = np.array([world.reading_deg(prefix) for _ in range(n)])
        single = np.array(
            [
                (s[f"{prefix}_x_deg"], s[f"{prefix}_y_deg"])
                for s in (world.sample() for _ in range(n))
            ]
        )
        # noisy (to the sensor's resolution), not repeated
        assert np.count_nonzero(np.diff(batched[:, 0])) > n // 4
        spread_b, spread_s = batched.std(axis=0), single.std(axis=0)
        assert np.all(spread_b > 0.6 * spread_s) and np.all(spread_b < 1.6 * spread_s), (
            spread_b,
            spread_s,
        )
        limit = 5 * np.sqrt((spread_b**2 + spread_s**2) / n)
        assert np.all(np.abs(batched.mean(axis=0) - single.mean(axis=0)) < limit)


def test_a_move_is_seen_by_the_very_next_reading() -> None:
    world = _world()
    # a batch is under way
    before = [world.reading_deg("ref") for _ in range(READINGS_PER_BATCH // 2)]
    pulses = round(2.0 / world.bench.pulse_x_deg)
    _move(world, 1, pulses)
    # the sensor has followed the table (its time constant)
    world.clock.sleep_blocking(world.settling.lasts_s())
    x_after, _ = world.reading_deg("ref")
    expected = world.sample(noisy=False)["ref_x_deg"]
    assert abs(x_after - expected) < 0.01
    assert abs(x_after - before[-1][0]) > 1.5
