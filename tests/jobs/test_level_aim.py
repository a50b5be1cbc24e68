"""Levelling's aim rule against a stage whose every move lands with a fresh positioning error: the
mean of the offsets seen so far takes out the record's local error without chasing that noise."""

from __future__ import annotations

import numpy as np

from service.jobs.level import next_aim

REPEATABILITY_DEG = 0.0025  # 1 sigma per axis, the seed 000 presets'
RECORD_ERROR_DEG = np.array([0.004, -0.003])  # what the record gets wrong where the stage stands


def final_errors(rule, read_backs: int, runs: int, rng: np.random.Generator) -> np.ndarray:
    """The error of the table's tilt after `read_backs` read-backs and one more move, per run."""
    target = (0.5, -0.25)
    errors = np.empty((runs, 2))
    for run in range(runs):
        aim, offsets = target, []
        for _ in range(read_backs):
            achieved = np.add(aim, RECORD_ERROR_DEG) + rng.normal(0, REPEATABILITY_DEG, 2)
            offsets.append((achieved[0] - aim[0], achieved[1] - aim[1]))
            aim = rule(target, offsets, aim)
        errors[run] = np.add(aim, RECORD_ERROR_DEG) + rng.normal(0, REPEATABILITY_DEG, 2) - target
    return errors


def mean_of_offsets(target, offsets, aim):
    return next_aim(target, offsets)


def last_offset(target, offsets, aim):
    """Aim again by the last remaining error alone (integral control: aim + (target - achieved))."""
    return target[0] - offsets[-1][0], target[1] - offsets[-1][1]


def test_the_record_error_is_taken_out_and_the_spread_falls_to_the_stage_repeatability():
    rng = np.random.default_rng()
    for read_backs in (1, 2, 4, 8):
        errors = final_errors(mean_of_offsets, read_backs, 4000, rng)
        # no bias left: the mean error within 5 standard errors of zero
        sd_expected = REPEATABILITY_DEG * np.sqrt(1 + 1 / read_backs)
        assert np.all(np.abs(errors.mean(axis=0)) < 5 * sd_expected / np.sqrt(4000)), errors.mean(0)
        # spread sigma·sqrt(1 + 1/k) after k read-backs (4,000 runs: sd known to about 1 %)
        np.testing.assert_allclose(errors.std(axis=0), sd_expected, rtol=0.06)


def test_chasing_the_last_offset_keeps_twice_the_variance():
    rng = np.random.default_rng()
    chased = final_errors(last_offset, 8, 4000, rng).std(axis=0)
    averaged = final_errors(mean_of_offsets, 8, 4000, rng).std(axis=0)
    np.testing.assert_allclose(chased, REPEATABILITY_DEG * np.sqrt(2), rtol=0.06)
    assert np.all(averaged < 0.85 * chased), (averaged, chased)
