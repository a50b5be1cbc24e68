"""`--bench FILE` through the console script: a bench configuration (TOML) or a scenario file
(JSON)."""

import json

import numpy as np
import pytest

from service.calibration.registry import get_method
from service.io.model_files import read_model
from service.scenarios import parse_scenario, run_scenario
from tests.helpers.benches import GRID, PERIODIC_X, scenario
from tests.helpers.cli import tiltlab

BENCH_TOML = """
[benches.wide-worms]
kind = "stage"

[benches.wide-worms.hardware]
upper_gear_ratio = 180
lower_gear_ratio = 360

[benches.wide-worms.roles.reference_sensor]
port = "/dev/ttyUSB0"

[benches.wide-worms.roles.measurement_sensor]
port = "/dev/ttyUSB1"

[benches.wide-worms.roles.stage]
port = "/dev/ttyUSB2"
"""


@pytest.fixture(scope="module")
def benches(tmp_path_factory):
    d = tmp_path_factory.mktemp("benches")
    for name in ("seed000", "180-360"):
        (d / f"{name}.json").write_text(json.dumps(scenario(name, PERIODIC_X, GRID)))
        p = tiltlab("simulate", "--scenario", f"{name}.json", "--out", f"{name}.csv", cwd=d)
        assert p.returncode == 0, p.stderr
    (d / "bench.toml").write_text(BENCH_TOML)
    return d


def _correction_rms(model_path, bench: str) -> float:
    """RMS of the corrected measurement readings against the true table tilt on a fresh run of the
    bench."""
    model = read_model(model_path)
    run = run_scenario(parse_scenario(scenario(bench, PERIODIC_X, GRID)), seed=777)
    out = get_method("stage", "kinematic").correct(model, run.columns)
    err = np.concatenate(
        [out["tilt_x_deg"] - run.truth["tilt_x_deg"], out["tilt_y_deg"] - run.truth["tilt_y_deg"]]
    )
    return float(np.sqrt(np.mean(err**2)))


@pytest.mark.parametrize("bench_file", ["bench.toml", "180-360.json"])
def test_kinematic_with_the_bench_is_as_accurate_as_on_seed000(benches, bench_file):
    p = tiltlab(
        "calibrate",
        "--kind",
        "stage",
        "--method",
        "kinematic",
        "--input",
        "180-360.csv",
        "--bench",
        bench_file,
        "--out",
        "m.json",
        cwd=benches,
    )
    assert p.returncode == 0, p.stderr
    assert "assumed" not in p.stderr
    state = json.loads((benches / "m.json").read_text())["state"]
    assert state["bench"]["upper_gear_ratio"] == 180 and state["bench"]["lower_gear_ratio"] == 360
    assert bench_file in state["bench_source"]
    p = tiltlab(
        "calibrate",
        "--kind",
        "stage",
        "--method",
        "kinematic",
        "--input",
        "seed000.csv",
        "--out",
        "s.json",
        cwd=benches,
    )
    assert p.returncode == 0, p.stderr
    assert "seed 000 bench was assumed" in p.stderr
    assert json.loads((benches / "s.json").read_text())["state"]["bench_source"].startswith(
        "assumed"
    )
    other, seed000 = (
        _correction_rms(benches / "m.json", "180-360"),
        _correction_rms(benches / "s.json", "seed000"),
    )
    assert other <= 1.2 * seed000, (other, seed000)


@pytest.mark.parametrize(
    "command",
    [("calibrate", "--kind", "stage", "--method", "kinematic"), ("discrepancy", "--kind", "stage")],
)
def test_other_bench_without_the_bench_is_refused_in_one_line(benches, command):
    p = tiltlab(*command, "--input", "180-360.csv", "--out", "r.json", cwd=benches)
    assert p.returncode == 2
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "not a whole number" in lines[0] and "--bench" in lines[0]
    assert not (benches / "r.json").exists()


def test_discrepancy_with_the_bench_names_the_periodic_error_and_records_the_bench(benches):
    p = tiltlab(
        "discrepancy",
        "--kind",
        "stage",
        "--input",
        "180-360.csv",
        "--bench",
        "bench.toml",
        "--out",
        "rep.json",
        cwd=benches,
    )
    assert p.returncode == 0, p.stderr
    rep = json.loads((benches / "rep.json").read_text())
    assert "periodic_error" in rep["named_effects"]
    mag = next(s["magnitude"] for s in rep["steps"] if s["effect"] == "periodic_error")
    assert mag["x_amp_deg"]["value"] == pytest.approx(0.010, abs=0.0015)
    assert (
        rep["bench"]["worm_period_x_deg"] == pytest.approx(2.0)
        and "bench.toml" in rep["bench"]["source"]
    )
    assert "worm periods 2°" in (benches / "rep.html").read_text()


def test_bench_refused_for_kinds_without_stages_and_for_unknown_files(benches):
    p = tiltlab(
        "discrepancy",
        "--kind",
        "scale",
        "--input",
        "180-360.csv",
        "--bench",
        "bench.toml",
        "--out",
        "x.json",
        cwd=benches,
    )
    assert p.returncode == 2 and "kind 'scale' has none" in p.stderr
    p = tiltlab(
        "calibrate",
        "--kind",
        "stage",
        "--method",
        "kinematic",
        "--input",
        "180-360.csv",
        "--bench",
        "nothing.toml",
        "--out",
        "x.json",
        cwd=benches,
    )
    assert p.returncode == 2 and "nothing.toml" in p.stderr
    (benches / "bench.yaml").write_text("x")
    p = tiltlab(
        "calibrate",
        "--kind",
        "stage",
        "--method",
        "kinematic",
        "--input",
        "180-360.csv",
        "--bench",
        "bench.yaml",
        "--out",
        "x.json",
        cwd=benches,
    )
    assert p.returncode == 2 and ".toml" in p.stderr
