"""The seed 000 rerun writes its report and figures (smoke test on two seeds; the committed report
uses 30)."""

from service.reproduce import seed000


def test_seed000_report_is_written(tmp_path):
    res = seed000.run(tmp_path, seeds=(0, 1))
    text = (tmp_path / "seed000.md").read_text(encoding="utf-8")
    for needle in (
        "0.559",
        "0.025",
        "0.013",
        "Kinematic against the oracle",
        "forward form against the exact inverse",
        "coupling",
        "axis-transform",
        "oracle",
    ):
        assert needle in text
    for name in res["figures"]:
        assert (tmp_path / name).stat().st_size > 10_000 and f"({name})" in text
    assert res["homography_flow_max"][0] <= 0.025 and res["homography_flow_max"][1] <= 0.013
    assert 0.2 < res["uncorrected_max"][0] < 1.0
