"""The simulated stage stands as a stage does: its positioning error (a repeatability) is drawn once
per move, shared by both sensors on the table and constant while the stage stands; each sensor's
noise is its own per reading; and the world's true tilt is the table as it stands, the positioning
error included."""

from __future__ import annotations

import numpy as np

from service.clock import Clock
from service.instruments import controller as ctl
from service.instruments.sim.world import StageWorld, stage_scenario
from tests.helpers.waiting import eventually

READINGS = 400


def _world(seed: int) -> StageWorld:
    scenario = stage_scenario("seed000").model_copy(update={"seed": seed})
    world = StageWorld(scenario, Clock(1000.0))
    for axis in world.axes.values():
        axis.homed = True
    return world


def _move(world: StageWorld, axis: int, target_pulses: int) -> None:
    assert world.axes[axis].move_to(target_pulses) == ctl.ERR_NONE
    eventually(
        lambda: world.axes[axis].state == ctl.STATE_READY,
        timeout_s=30,
        what="the simulated move to end",
    )
    # at rest: the preset's settling transient has died out
    world.clock.sleep_blocking(world.settling.lasts_s())


def _noise(world: StageWorld, sensor: str) -> float:
    return float(world.effects.get("noise", f"{sensor}_sigma_deg"))


def test_at_rest_the_sensors_differ_by_their_own_noise_and_the_table_stands_still() -> None:
    for seed in (1, 2, 3):
        world = _world(seed)
        _move(world, 1, round(1.5 / world.bench.pulse_x_deg))
        truth = world.true_tilt_deg()
        ref = np.array([world.reading_deg("ref") for _ in range(READINGS)])
        meas = np.array([world.reading_deg("meas") for _ in range(READINGS)])
        assert world.true_tilt_deg() == truth  # the table does not move while it stands
        combined = np.hypot(_noise(world, "ref"), _noise(world, "meas"))
        difference_sd = (meas - ref).std(axis=0, ddof=1)
        # a table that jittered per reading and per sensor would add 2 x stage_sigma_deg**2 (0.0025
        # deg) here
        assert np.all(difference_sd > 0.8 * combined) and np.all(difference_sd < 1.25 * combined), (
            difference_sd,
            combined,
        )
        # each sensor scatters by its own noise about what it reads of the table as it stands
        for readings, sensor in ((ref, "ref"), (meas, "meas")):
            spread = readings.std(axis=0, ddof=1)
            assert np.all(spread < 1.25 * _noise(world, sensor)), (sensor, spread)
            still = world.sample(noisy=False)
            expected = np.array([still[f"{sensor}_x_deg"], still[f"{sensor}_y_deg"]])
            assert np.all(
                np.abs(readings.mean(axis=0) - expected)
                < 5 * _noise(world, sensor) / np.sqrt(READINGS)
            )


def test_every_move_draws_the_stands_positioning_error_once() -> None:
    world = _world(7)
    there, back = round(1.0 / world.bench.pulse_x_deg), round(2.0 / world.bench.pulse_x_deg)
    truths, ref_means = [], []
    for _ in range(40):  # to the same commanded pose from the same side, forty times
        _move(world, 1, there)
        _move(world, 1, back)
        truths.append(world.true_tilt_deg()[0])
        ref_means.append(np.mean([world.reading_deg("ref")[0] for _ in range(20)]))
    sigma = float(world.effects.get("noise", "stage_sigma_deg"))
    truth_sd = float(np.std(truths, ddof=1))
    assert 0.6 * sigma < truth_sd < 1.5 * sigma, (truth_sd, sigma)
    # the reference follows the table's stand to stand: what is left is its own noise of a
    # 20-reading mean
    left = np.asarray(ref_means) - np.asarray(truths)
    assert float(np.std(left, ddof=1)) < 3 * _noise(world, "ref") / np.sqrt(20) + 1e-4
