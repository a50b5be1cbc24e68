"""Which stages a named worm error is fitted on: a stage's sine and cosine judged together, at a
level for both stages. A stage the grid samples on a short arc of its worm has a large, correlated
covariance there; a term taken on one look at it is a chance sinusoid that levelling extrapolates
(the 7 x 7 grid 2.2 deg apart over the upper stage's 1.125 deg worm: +-48 deg of its phase)."""

from __future__ import annotations

import numpy as np
from scipy import stats

from service.discrepancy.adopt import WORM_STAGE_ALPHA, worm_axes_seen

LABELS = ["x_sin_deg", "x_cos_deg", "y_sin_deg", "y_cos_deg"]


def _covariance(x_sd: float, x_corr: float, y_sd: float) -> np.ndarray:
    cov = np.zeros((4, 4))
    cov[:2, :2] = x_sd**2 * np.array([[1.0, x_corr], [x_corr, 1.0]])
    cov[2:, 2:] = y_sd**2 * np.eye(2)
    return cov


def test_a_real_worm_is_seen_and_a_chance_term_on_a_poorly_sampled_stage_is_not() -> None:
    # the lower stage's worm (0.012 deg, determined to 0.0007) beside nothing on the upper stage,
    # whose sine comes out 3.2 of its standard uncertainties from zero on a correlated pair
    cov = _covariance(0.0066, 0.9, 0.0007)
    values = np.array([3.2 * 0.0066, 0.9 * 3.2 * 0.0066, 0.0041, -0.0113])
    assert worm_axes_seen(LABELS, values, cov) == ["y"]
    # the same terms far beyond chance on both stages: both
    values[:2] = [0.03, -0.01]
    assert worm_axes_seen(LABELS, values, cov) == ["x", "y"]


def test_with_nothing_beyond_chance_the_clearest_stage_is_kept() -> None:
    cov = _covariance(0.001, 0.0, 0.001)
    assert worm_axes_seen(LABELS, np.array([0.0005, 0.0, 0.002, 0.0]), cov) == ["y"]


def test_a_term_the_points_do_not_determine_is_left_out_of_its_stage() -> None:
    # two phases of the lower stage's worm: its cosine held (zero variance), the sine judged alone
    cov = _covariance(0.001, 0.0, 0.001)
    cov[3, 3] = 0.0
    assert worm_axes_seen(LABELS, np.array([0.0, 0.0, 0.01, 0.0]), cov) == ["y"]


def test_a_stage_without_a_worm_is_taken_for_one_at_the_stated_rate() -> None:
    # fitted terms as the fit's covariance says they scatter, with no worm on the upper stage:
    # that stage is seen in WORM_STAGE_ALPHA / 2 of diagnoses (the level is for both stages)
    rng = np.random.default_rng()
    cov = _covariance(0.0066, 0.95, 0.0007)
    draws = 30_000
    seen = 0
    for x_terms in rng.multivariate_normal(np.zeros(2), cov[:2, :2], draws):
        values = np.array([*x_terms, 0.0041, -0.0113])
        seen += "x" in worm_axes_seen(LABELS, values, cov)
    rate = WORM_STAGE_ALPHA / 2
    # within the binomial's 1e-4 two-sided bounds of the stated rate
    lo, hi = stats.binom.ppf([5e-5, 1 - 5e-5], draws, rate)
    assert lo <= seen <= hi, (seen, draws * rate)
    # one look at the larger term, 3 standard uncertainties (the rule this replaced), takes it for
    # a worm 7.5 times as often at this correlation (11 times for independent terms)
    z = np.abs(rng.multivariate_normal(np.zeros(2), cov[:2, :2], draws)) / 0.0066
    assert np.mean(z.max(axis=1) > 3.0) > 5 * rate
