"""The expanded uncertainty each offline method states covers the simulated truth about 95 % of the
time: not 0.99 (a U too wide, e.g. the reference's noise counted in a corrected reading) and not
0.85 (one that leaves errors out).

Pooled over enough validation points (1,300-2,000 per case) that a true 0.95 lies more than five
binomial standard deviations inside [0.92, 0.98] and a true 0.99 falls outside it.
benchmarks/coverage.py gives the full table (200 realisations per case, per axis and per angle);
docs/uncertainty.md has its figures.
"""

import pytest

from service.reproduce.coverage import (
    rotation_coverage,
    scale_coverage,
    stage_coverage,
    turntable_coverage,
)

CASES = {
    "stage homography": lambda: stage_coverage("homography", "ref noise stated", 10, seed0=1000),
    "stage kinematic": lambda: stage_coverage("kinematic", "ref noise stated", 10, seed0=1000),
    # one reading a stand and the reference's noise not stated: the three-way estimate of the
    # reading noise (about 0.94-0.97 over four sets of ten realisations each)
    "stage homography, ref noise unknown": lambda: stage_coverage(
        "homography", "ref noise unknown", 10, seed0=1000
    ),
    "stage kinematic, ref noise unknown": lambda: stage_coverage(
        "kinematic", "ref noise unknown", 10, seed0=1000
    ),
    "stage kinematic, 3 readings per stand": lambda: stage_coverage(
        "kinematic", "3 readings per stand", 8, seed0=1000
    ),
    # a model without zero offsets: its error is mostly a bias it states (U the folded normal's
    # 95 % point, not k × the rms); pooled coverage 0.941-0.959 over five sets of ten
    "stage axis-transform": lambda: stage_coverage(
        "axis-transform", "ref noise stated", 10, seed0=1000
    ),
    "stage axis-transform, 3 readings per stand": lambda: stage_coverage(
        "axis-transform", "3 readings per stand", 10, seed0=1000
    ),
    # one reading a stand, nothing stated: the three-way estimate against a projective stage
    # prediction (0.956-0.965 over five sets of ten)
    "stage axis-transform, ref noise unknown": lambda: stage_coverage(
        "axis-transform", "ref noise unknown", 10, seed0=1000
    ),
    # the paper's baseline corrects nothing of the measurement sensor: U follows the misfit's
    # envelope over the pose (pooled 0.935-0.947 over six sets of ten; per axis 0.927-0.956)
    "stage coupling": lambda: stage_coverage("coupling", "ref noise stated", 10, seed0=1000),
    # 200 sweeps each (5,000 angles; 3,600 for direct): the angles of one calibration share its
    # errors, so fewer sweeps scatter more than their count suggests (64 sweeps: 0.966-0.983 over
    # six sets; 200: 0.960-0.975)
    "rotation iodsra": lambda: rotation_coverage("iodsra", "seed002-b55", 200, seed0=1000),
    "rotation iodsra-combined": lambda: rotation_coverage(
        "iodsra-combined", "seed002-b55", 200, seed0=1000
    ),
    # the paper's baseline: its arcs show its plane's error as a known bias (0.964-0.974 over six
    # sets of 200)
    "rotation direct": lambda: rotation_coverage("direct", "seed002-sim", 200, seed0=1000),
    "scale poly1": lambda: scale_coverage("poly1", 130, seed0=1000),
    "turntable reversal": lambda: turntable_coverage(100, seed0=1000),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_offline_method_covers_about_95_percent(case):
    rows = CASES[case]()
    hits, n = sum(r.hits for r in rows), sum(r.n for r in rows)
    assert n >= 1200, n
    assert 0.92 <= hits / n <= 0.98, (case, hits / n, n)
    # and the errors are the size U says, not merely inside it: rms(error / U) near 1/1.96 (for
    # an error about zero; axis-transform's sits near its bias and coupling's near its misfit's
    # envelope, just inside U: about 0.95)
    if "axis-transform" in case or "coupling" in case:
        for r in rows:
            assert 0.85 <= r.rms_error_over_u <= 1.0, (case, r)
        return
    for r in rows if rows[0].kind != "rotation" else []:
        assert 0.40 <= r.rms_error_over_u <= 0.60, (case, r)
