"""The reproduction report's verdicts follow the numbers it states: change the numbers and the
sentence changes (nothing typed in)."""

from __future__ import annotations

from service.reproduce.seed000 import KINDS, ORACLE_RATIO_TARGET, PAPER_AFTER, conclusions


def _numbers(h_max_x: float, ratio: float, x_tilt_error: float):  # type: ignore[no-untyped-def]
    means = {k: {"homography": {"max_x": h_max_x, "max_y": PAPER_AFTER[1] / 2}} for k in KINDS}
    ratios = {
        grid: {"rms_x": {"mean": 1.0, "worst": 1.1}, "max_y": {"mean": ratio, "worst": ratio}}
        for grid in ("paper", "offset")
    }
    fwd = {"max_abs_x_tilt_error_deg": x_tilt_error}
    return means, ratios, fwd


def test_homography_verdict_follows_its_maxima() -> None:
    assert "meets" in conclusions(*_numbers(PAPER_AFTER[0] * 0.5, 1.0, 0.006))["homography"]
    said = conclusions(*_numbers(PAPER_AFTER[0] * 1.5, 1.0, 0.006))["homography"]
    assert "does not meet" in said and "150%" in said


def test_oracle_verdict_names_what_exceeds_the_target() -> None:
    assert (
        "stays within" in conclusions(*_numbers(0.01, ORACLE_RATIO_TARGET - 0.1, 0.006))["oracle"]
    )
    said = conclusions(*_numbers(0.01, ORACLE_RATIO_TARGET + 0.3, 0.006))["oracle"]
    assert "exceeds" in said and "max y" in said and "1.500" in said


def test_eq10_share_of_the_budget_is_computed() -> None:
    assert "24%" in conclusions(*_numbers(0.01, 1.0, 0.006))["eq10"]
    assert "80%" in conclusions(*_numbers(0.01, 1.0, 0.020))["eq10"]
