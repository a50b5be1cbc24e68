"""`tiltlab simulate` as other software calls it: a subprocess, files, exit status, stderr."""

import json
import subprocess
import sys

import pytest

from service.io.datasets import read_dataset

REQUIRED = {
    "seed000": (
        "stage",
        (
            "stage_x_deg",
            "stage_y_deg",
            "ref_x_deg",
            "ref_y_deg",
            "meas_x_deg",
            "meas_y_deg",
            "dir_x",
            "dir_y",
            "temp_c",
            "t_s",
            "point",
        ),
    ),
    "seed002-b55": ("rotation", ("sx", "sy", "sz", "theta_ref_deg")),
    "seed002-b75": ("rotation", ("sx", "sy", "sz", "theta_ref_deg")),
    "seed002-sim": ("rotation", ("sx", "sy", "sz", "theta_ref_deg")),
    "seed003": ("scale", ("ref_arcsec", "reading")),
    "seed004": (
        "turntable",
        ("azimuth_deg", "n1_a", "n2_a", "n1_b", "n2_b", "ref_north_arcsec", "ref_east_arcsec"),
    ),
}


def tiltlab(*args):
    return subprocess.run([sys.executable, "-m", "service", *args], capture_output=True, text=True)


@pytest.mark.parametrize("preset", sorted(REQUIRED))
def test_each_preset_writes_a_valid_dataset_of_its_kind(tmp_path, preset):
    out = tmp_path / "x.csv"
    r = tiltlab("simulate", "--scenario", preset, "--out", str(out))
    assert r.returncode == 0, r.stderr
    kind, cols = REQUIRED[preset]
    ds = read_dataset(out, kind, cols)  # the product's own strict reader accepts it
    assert ds.n_rows > 0


def test_seed_option_changes_the_noise_only(tmp_path):
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    assert (
        tiltlab("simulate", "--scenario", "seed000", "--out", str(a), "--seed", "5").returncode == 0
    )
    assert (
        tiltlab("simulate", "--scenario", "seed000", "--out", str(b), "--seed", "6").returncode == 0
    )
    la, lb = a.read_text().splitlines(), b.read_text().splitlines()
    assert la[0] == lb[0] and la[1].split(",")[:5] == lb[1].split(",")[:5] and la[1] != lb[1]


@pytest.mark.parametrize(
    "scenario,field",
    [
        (
            {"kind": "stage", "grid": {"x_deg": [0], "y_deg": [0]}, "effects": {"wobble": {}}},
            "effects.wobble",
        ),
        (
            {
                "kind": "stage",
                "grid": {"x_deg": [0], "y_deg": [0]},
                "effects": {"backlash": {"y_deg": 2}},
            },
            "effects.backlash.y_deg",
        ),
        ({"kind": "stage", "effects": {}}, "grid"),
    ],
)
def test_bad_scenario_exits_2_with_one_line_and_writes_nothing(tmp_path, scenario, field):
    sc = tmp_path / "bad.json"
    sc.write_text(json.dumps(scenario))
    out = tmp_path / "x.csv"
    r = tiltlab("simulate", "--scenario", str(sc), "--out", str(out))
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and f"field {field}" in lines[0] and "Traceback" not in r.stderr
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["bad.json"]


def test_unknown_preset_and_broken_json(tmp_path):
    r = tiltlab("simulate", "--scenario", "seed999", "--out", str(tmp_path / "x.csv"))
    assert r.returncode == 2 and "no such preset or file" in r.stderr
    bad = tmp_path / "b.json"
    bad.write_text("{not json")
    r = tiltlab("simulate", "--scenario", str(bad), "--out", str(tmp_path / "x.csv"))
    assert r.returncode == 2 and "not valid JSON" in r.stderr


def test_list_gives_each_description_in_full():
    import subprocess
    import sys

    from service.scenarios import load_scenario, preset_names

    out = subprocess.run(
        [sys.executable, "-m", "service", "simulate", "--list"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**__import__("os").environ, "COLUMNS": "80"},
    )
    assert out.returncode == 0, out.stderr
    words = " ".join(out.stdout.split())
    assert "…" not in out.stdout
    for name in preset_names():
        about = " ".join((load_scenario(name).description or "").split())
        assert about in words, (name, about)
