"""The discrepancy workflow's hand-written statistics against scipy.stats (which it does not import,
for speed)."""

import numpy as np
import pytest
from scipy import stats as sps

from service.calibration.methods.scale import f_test
from service.discrepancy import stats


@pytest.mark.parametrize("x, k", [(0.5, 1), (3.84, 1), (12.0, 4), (80.0, 60)])
def test_chi2_sf(x, k):
    assert stats.chi2_sf(x, k) == pytest.approx(sps.chi2.sf(x, k), rel=1e-10)


@pytest.mark.parametrize("f, d1, d2", [(0.3, 1, 10), (4.96, 1, 10), (2.5, 4, 150), (9.0, 2, 7)])
def test_f_sf(f, d1, d2):
    assert stats.f_sf(f, d1, d2) == pytest.approx(sps.f.sf(f, d1, d2), rel=1e-10)


@pytest.mark.parametrize("t, df", [(0.2, 3), (2.228, 10), (-3.1, 40.5)])
def test_t_two_sided(t, df):
    assert stats.t_two_sided(t, df) == pytest.approx(2 * sps.t.sf(abs(t), df), rel=1e-10)


def test_welch_t_and_pearson():
    rng = np.random.default_rng(5)
    a, b = rng.normal(0.0, 1.0, 17), rng.normal(0.6, 2.0, 23)
    t, p = stats.welch_t(a, b)
    ref = sps.ttest_ind(a, b, equal_var=False)
    assert t == pytest.approx(ref.statistic, rel=1e-10) and p == pytest.approx(ref.pvalue, rel=1e-8)
    x = rng.normal(size=30)
    y = 0.4 * x + rng.normal(size=30)
    r, p = stats.pearson(x, y)
    ref = sps.pearsonr(x, y)
    assert r == pytest.approx(ref.statistic, rel=1e-10) and p == pytest.approx(ref.pvalue, rel=1e-8)


def test_scale_f_test_of_an_added_term():
    out = f_test(rss_small=150.0, rss_big=100.0, dof_big=9)
    F = (150.0 - 100.0) / (100.0 / 9)
    assert out["F"] == pytest.approx(F) and out["p_value"] == pytest.approx(
        sps.f.sf(F, 1, 9), rel=1e-10
    )


def test_runs_test_z_against_its_normal_approximation():
    r = np.array([1.0, 2, 3, -1, -2, 1, 2, -3, -1, -2, 3, 1, -1, 2])
    t = stats.runs_test(r, np.arange(r.size), "x")
    s = np.sign(r - np.median(r))
    s = s[s != 0]
    n1, n2 = int(np.sum(s > 0)), int(np.sum(s < 0))
    runs = 1 + int(np.sum(np.diff(s) != 0))
    mu = 2 * n1 * n2 / (n1 + n2) + 1
    var = 2 * n1 * n2 * (2 * n1 * n2 - n1 - n2) / ((n1 + n2) ** 2 * (n1 + n2 - 1))
    assert t.p_value == pytest.approx(sps.norm.cdf((runs - mu) / np.sqrt(var)), rel=1e-10)
