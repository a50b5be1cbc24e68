"""`tiltlab discrepancy --adopt MODEL.json`: the offline last step. The model it writes is the
kinematic calibration with the named effects added; `tiltlab level` with it aims closer to the truth
than without."""

import csv
import json

import numpy as np
import pytest

from service.calibration.methods.stage.chain import ChainModel
from service.io.model_files import read_model
from service.physics.stage import StageBench
from service.scenarios import parse_scenario
from service.scenarios.run import effect_set, hardware_of
from tests.helpers.benches import GRID, PERIODIC_X, scenario
from tests.helpers.cli import tiltlab

TARGETS = [(1.3, -2.1), (-4.7, 3.3), (5.9, 0.7), (-2.6, -5.4), (3.5, 4.9), (-9.1, 8.2)]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("adopt")
    for name, effects in (("periodic", PERIODIC_X), ("clean", None)):
        (d / f"{name}.json").write_text(json.dumps(scenario("180-360", effects, GRID)))
        p = tiltlab("simulate", "--scenario", f"{name}.json", "--out", f"{name}.csv", cwd=d)
        assert p.returncode == 0, p.stderr
    with open(d / "targets.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["target_x_deg", "target_y_deg"])
        w.writerows(TARGETS)
    return d


def _levelling_error(d, model: str) -> float:
    """Mean distance of the true table tilt, at the commands `tiltlab level` gives, from the
    targets."""
    p = tiltlab(
        "level",
        "--model",
        model,
        "--targets",
        "targets.csv",
        "--out",
        f"{model}.commands.csv",
        cwd=d,
    )
    assert p.returncode == 0, p.stderr
    with open(d / f"{model}.commands.csv") as fh:
        rows = list(csv.DictReader(fh))
    sc = parse_scenario(scenario("180-360", PERIODIC_X, GRID))
    truth = ChainModel(hardware_of(sc), effect_set(sc))
    x = np.array([float(r["stage_x_deg"]) for r in rows])
    y = np.array([float(r["stage_y_deg"]) for r in rows])
    tx, ty = truth.tilt(x, y, 1.0, 1.0)
    t = np.array(TARGETS)
    return float(np.mean(np.hypot(tx - t[:, 0], ty - t[:, 1])))


def test_adopt_writes_the_model_with_the_named_effect_and_levels_closer(runs):
    p = tiltlab(
        "discrepancy",
        "--kind",
        "stage",
        "--input",
        "periodic.csv",
        "--bench",
        "periodic.json",
        "--baseline",
        "kinematic",
        "--out",
        "rep.json",
        "--adopt",
        "adopted.json",
        cwd=runs,
    )
    assert p.returncode == 0, p.stderr
    rep = json.loads((runs / "rep.json").read_text())
    assert "periodic_error" in rep["named_effects"]
    model = read_model(runs / "adopted.json")
    assert model.method == "kinematic" and model.state["added_effects"] == ["periodic_error"]
    assert model.state["diagnosis"]["report"] == "rep.json" and model.provenance["command"]
    # fitted as a sine/cosine pair (linear, determined from a start at zero); amplitude and phase
    # derived from it
    assert np.hypot(
        model.value("periodic_error.x_sin_deg"), model.value("periodic_error.x_cos_deg")
    ) == pytest.approx(0.010, abs=0.002)
    worm = model.fit["periodic_error"]["x"]
    assert worm["amplitude_deg"] == pytest.approx(0.010, abs=0.002) and worm["u_amplitude_deg"] > 0
    assert worm["phase_deg"] == pytest.approx(40.0, abs=3 * worm["u_phase_deg"] + 2.0)
    assert StageBench(**model.state["bench"]).upper_gear_ratio == 180
    p = tiltlab(
        "calibrate",
        "--kind",
        "stage",
        "--method",
        "kinematic",
        "--input",
        "periodic.csv",
        "--bench",
        "periodic.json",
        "--out",
        "plain.json",
        cwd=runs,
    )
    assert p.returncode == 0, p.stderr
    assert _levelling_error(runs, "adopted.json") <= 0.6 * _levelling_error(runs, "plain.json")


def test_nothing_named_writes_nothing(runs):
    p = tiltlab(
        "discrepancy",
        "--kind",
        "stage",
        "--input",
        "clean.csv",
        "--bench",
        "clean.json",
        "--baseline",
        "kinematic",
        "--out",
        "clean-rep.json",
        "--adopt",
        "clean-model.json",
        cwd=runs,
    )
    assert p.returncode == 2 and "nothing to adopt" in p.stderr, p.stderr
    assert not any(
        (runs / f).exists() for f in ("clean-rep.json", "clean-rep.html", "clean-model.json")
    )
