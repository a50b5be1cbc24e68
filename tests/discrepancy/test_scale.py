"""Scale kind: seed 003's Table 1 (baseline poly1, candidate a higher degree) and simulated
outputs."""

from pathlib import Path

import numpy as np
import pytest

from service.calibration.registry import FitOptions, get_method
from service.discrepancy.scale import scale_report
from service.io.datasets import read_dataset
from service.scenarios import load_scenario, parse_scenario, run_scenario

ROOT = Path(__file__).resolve().parents[2]
TABLE1 = ROOT / "service" / "calibration" / "data" / "seed003_table1.csv"
# seed 003, Table 1: T3A angle change (arcsec) and ADC0 reading (counts)
REF = np.array([0, 315, 666, 1015, 1345, 1701, 1965, 2328, 2615, 2871, 3210, 3461.0])
READING = np.array([16, 378, 739, 1131, 1518, 1961, 2244, 2604, 3004, 3277, 3680, 3924.0])


def table1_columns():
    if TABLE1.exists():
        return read_dataset(
            TABLE1, "scale", (("ref_arcsec", "ref_deg"), "reading"), ("point",)
        ).arrays()
    return {"ref_arcsec": REF, "reading": READING}


def test_table1_supports_a_straight_line_only():
    cols = table1_columns()
    assert np.array_equal(cols["ref_arcsec"], REF) and np.array_equal(cols["reading"], READING)
    rep, _, _ = scale_report(cols)
    assert rep["baseline"] == "poly1" and rep["unit"] == "arcsec"
    assert rep["named_effects"] == []
    assert rep["supported_model"] == "poly1"
    # no repeats, no specification: 12 points, one pass
    assert rep["noise_source"] == "final residual"
    quad = next(c for c in rep["stop"]["candidates"] if c["effect"] == "sensor_nonlinearity")
    assert quad["p_value"] > 0.1 and quad["delta_bic"] > 0
    assert {s["effect"] for s in rep["skipped"]} == {"temperature_drift"}
    # same straight line as the calibration method poly1 (angle on reading, arcsec per count)
    model = get_method("scale", "poly1").fit(cols, FitOptions())
    slope = rep["baseline_fit"]["arcsec_per_count"]["value"]
    assert slope == pytest.approx(model.parameters["c1_arcsec_per_count"].value, rel=1e-9)
    assert rep["final_rms"][0] == pytest.approx(
        model.residuals["columns"]["angle_arcsec"]["rms"], rel=1e-9
    )


def _scale_run(effects, seed=0, repeats=1, temp_amp=0.0):
    sc = load_scenario("seed003").model_dump()
    sc["effects"] = {k: v for k, v in sc["effects"].items() if v is not None}
    sc["effects"].update(effects)
    sc["grid"] = {"ref_arcsec": {"start": 0, "stop": 3400, "count": 25}, "repeats": repeats}
    sc["environment"] = {"temp_c": 20.0, "temp_amp_c": temp_amp, "temp_period_h": 1.0}
    return run_scenario(parse_scenario(sc), seed=seed)


def test_simulated_quadratic_output_is_named_with_its_peak_in_arcsec():
    run = _scale_run({"sensor_nonlinearity": {"counts_per_arcsec2": 2e-5}})
    rep, _, _ = scale_report(run.columns)
    assert rep["named_effects"] == ["sensor_nonlinearity"]
    assert rep["supported_model"] == "poly2"
    mag = rep["steps"][0]["magnitude"]
    assert mag["degree"] == 2
    assert mag["peak_departure_arcsec"]["value"] > 3 * mag["peak_departure_arcsec"]["uncertainty"]


def test_straight_simulated_output_stays_poly1_and_repeats_give_the_noise():
    run = _scale_run({}, seed=4, repeats=2)
    rep, _, _ = scale_report(run.columns)
    assert rep["named_effects"] == []
    assert rep["noise_source"] == "repeated points"
