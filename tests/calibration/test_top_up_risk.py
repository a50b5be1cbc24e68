"""The adaptive plan's margin: how far below the target it aims, chosen for the least bench time
with the risk of a top-up pass weighed in. The probability of that pass is checked against draws
of what the fit does (each axis's residual variance on its own degrees of freedom, against that
axis's noise in the plan, from the first point's readings; the larger ratio stated), not against
its own formula."""

from __future__ import annotations

import numpy as np
import pytest

from service.calibration.adaptive_design import (
    NOISE_READINGS,
    PLAN_MARGINS,
    BenchNoise,
    BenchTimes,
    plan_adaptive,
    top_up_probability,
)
from service.calibration.methods.stage.common import MEAS_PARAMS


@pytest.mark.parametrize("share", [0.6, 0.7, 0.85, 0.95])
@pytest.mark.parametrize("n_points", [16, 30])
def test_top_up_probability_matches_draws_of_the_fits_variance(share, n_points):
    rng = np.random.default_rng(7)
    draws = 200_000
    per_axis = n_points - len(MEAS_PARAMS) / 2
    noise_dof = 2 * (NOISE_READINGS - 1)
    fit_axes = rng.chisquare(per_axis, (draws, 2)) / per_axis
    plan_axes = rng.chisquare(noise_dof, (draws, 2)) / noise_dof  # each axis's noise its own
    # the fit's prediction over the plan's is the square root of the larger axis's variance ratio
    drawn = np.mean(np.sqrt((fit_axes / plan_axes).max(axis=1)) > 1 / share)
    # 200,000 draws: a binomial standard error under 0.0012
    assert top_up_probability(share, n_points) == pytest.approx(drawn, abs=0.005)


def test_the_plan_weighs_readings_against_the_risk_of_a_second_pass():
    noise = BenchNoise(0.001, 0.001, 4e-5)
    chosen = {}
    for name, times in (("cheap", BenchTimes(settle_s=1.0)), ("dear", BenchTimes(settle_s=16.0))):
        plan = plan_adaptive((-12, 12), (-12, 12), 9, 9, 0.00033, noise, times)
        assert plan.margin in PLAN_MARGINS
        assert plan.predicted_u_deg <= plan.margin * plan.target_deg * (1 + 1e-9)
        # no other margin costs less, its second pass weighed by its probability
        each = [
            plan_adaptive((-12, 12), (-12, 12), 9, 9, 0.00033, noise, times, margins=(margin,))
            for margin in PLAN_MARGINS
        ]
        expected = [other.bench_seconds * (1 + other.top_up_probability) for other in each]
        assert plan.bench_seconds * (1 + plan.top_up_probability) == min(expected)
        # and the margin used so far (0.85) risked a second pass in about a third of the jobs
        assert each[PLAN_MARGINS.index(0.85)].top_up_probability > 0.3
        chosen[name] = plan
    # where a stand costs a long settling a second pass is dear: the plan aims lower, risks less
    assert chosen["dear"].margin <= chosen["cheap"].margin
    assert chosen["dear"].top_up_probability < 0.1
