"""The fastest simulation the simulated lines carry: at that speed-up every sensor's automatic
output fits in its line's share, one step faster it does not; the daemon refuses a faster one before
it starts."""

from __future__ import annotations

import pytest

from service.bench.startup import check_sim_speed
from service.config import Settings
from service.errors import InputError
from service.instruments import binary
from service.instruments.sim import (
    AUTO_OUTPUT_LINES,
    DEFAULT_OUTPUT_RATE_HZ,
    LINE_SHARE,
    SIM_BAUD,
    fastest_speed,
)


@pytest.mark.parametrize("kind", ["stage", "rotary"])
def test_the_fastest_speed_is_the_last_the_lines_carry(kind):
    limit, why = fastest_speed(kind)
    for _role, frame_bytes in AUTO_OUTPUT_LINES[kind]:
        line_frames_per_s = SIM_BAUD["binary"] / (10 * frame_bytes)
        assert 1 / binary.frame_time_s(frame_bytes, SIM_BAUD["binary"]) == pytest.approx(
            line_frames_per_s
        )
        assert limit * DEFAULT_OUTPUT_RATE_HZ <= LINE_SHARE * line_frames_per_s
    assert any(
        (limit + 1) * DEFAULT_OUTPUT_RATE_HZ > LINE_SHARE * SIM_BAUD["binary"] / (10 * frame_bytes)
        for _role, frame_bytes in AUTO_OUTPUT_LINES[kind]
    )
    assert "baud" in why and "frames a second" in why


def test_the_stage_bench_runs_up_to_28_times_real_time(tmp_path):
    check_sim_speed(Settings(data_dir=tmp_path, sim_speed=28))
    with pytest.raises(InputError, match="at most 28"):
        check_sim_speed(Settings(data_dir=tmp_path, sim_speed=29))


def test_a_bench_configuration_is_not_limited_by_the_simulated_lines(tmp_path):
    conf = tmp_path / "bench.toml"
    check_sim_speed(Settings(data_dir=tmp_path, sim_speed=500, bench_config=conf))
