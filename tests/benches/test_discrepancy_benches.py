"""The discrepancy workflow on benches other than seed 000's: a 0.010-deg periodic error of the
upper worm is named with its size and phase as on seed 000, given the bench; without it the data are
refused."""

import numpy as np
import pytest

from service.discrepancy.stage import stage_report
from service.errors import InputError
from service.scenarios import parse_scenario, run_scenario
from tests.helpers.benches import BENCHES, GRID, PERIODIC_X, noise_sigma_deg, scenario, stage_bench

SEEDS = (0, 1)


def _report(bench: str, baseline: str, seed: int, stated: bool = True):
    data = scenario(bench, PERIODIC_X, GRID)
    sensor = "meas" if bench == "mirrored-y" else "ref"
    cols = run_scenario(parse_scenario(data), seed=seed).columns
    rep, _, _ = stage_report(
        cols,
        sensor,
        baseline,
        noise_sigma_deg(data, sensor),
        bench=stage_bench(bench) if stated else None,
    )
    return rep


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("baseline", ["linear", "kinematic"])
@pytest.mark.parametrize("bench", list(BENCHES))
def test_periodic_error_found_at_its_size_and_phase_on_every_bench(bench, baseline, seed):
    rep = _report(bench, baseline, seed)
    assert set(rep["named_effects"]) - {"offaxis_coupling"} == {"periodic_error"}
    mag = next(s["magnitude"] for s in rep["steps"] if s["effect"] == "periodic_error")
    amp, phase = mag["x_amp_deg"], mag["x_phase_deg"]
    assert abs(amp["value"] - 0.010) <= 4 * amp["uncertainty"] and amp["uncertainty"] < 0.001
    assert abs(phase["value"] - 40.0) <= 4 * phase["uncertainty"] + 1.0
    assert f"{stage_bench(bench).worm_period_x_deg:g} deg" in amp["what"]
    assert rep["final_vs_noise"]["p_value"] > 0.01  # down to the noise, as on seed 000
    assert rep["bench"]["upper_gear_ratio"] == stage_bench(bench).upper_gear_ratio


@pytest.mark.parametrize("bench", ["180-360", "16-microsteps"])
def test_data_of_another_gearing_are_refused_without_the_bench(bench):
    with pytest.raises(InputError, match=r"not a whole number.*worm period.*--bench"):
        _report(bench, "linear", 0, stated=False)


def test_seed000_data_without_the_bench_say_it_was_assumed():
    rep = _report("seed000", "linear", 0, stated=False)
    assert rep["bench"]["source"].startswith("assumed")
    assert rep["bench"]["worm_period_x_deg"] == pytest.approx(1.125)
    assert np.isfinite(rep["final_rms"]).all()
