"""Every method's MODEL.json: valid against docs/model.schema.json and faithful after a round
trip."""

import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from service.calibration.model import CalibrationModel
from service.calibration.registry import FitOptions, get_method, methods_for
from service.scenarios import load_scenario, run_scenario

ROOT = Path(__file__).resolve().parents[2]
SCHEMA = json.loads((ROOT / "docs" / "model.schema.json").read_text())
PRESET_OF_KIND = {
    "stage": "seed000",
    "rotation": "seed002-b55",
    "scale": "seed003",
    "turntable": "seed004",
}
CASES = [(k, m) for k in ("stage", "rotation", "turntable") for m in methods_for(k)] + [
    ("scale", "poly1"),
    ("scale", "poly2"),
]


def _columns(kind, method):
    cols = {
        k: np.asarray(v, dtype=float)
        for k, v in run_scenario(load_scenario(PRESET_OF_KIND[kind])).columns.items()
    }
    m = get_method(kind, method)
    wanted = set()
    for item in (
        m.fit_required + m.fit_optional + m.correct_required + getattr(m, "correct_optional", ())
    ):
        wanted |= {item} if isinstance(item, str) else set(item)
    return m, {k: v for k, v in cols.items() if k in wanted}


def test_every_registered_kind_has_methods():
    for kind in ("stage", "rotation", "turntable"):
        assert methods_for(kind)


@pytest.mark.parametrize("kind,method", CASES, ids=[f"{k}-{m}" for k, m in CASES])
def test_model_file_is_valid_and_round_trips(kind, method):
    m, cols = _columns(kind, method)
    model = m.fit(cols, FitOptions())
    doc = json.loads(json.dumps(model.to_json_dict(), allow_nan=False))  # what lands on disk
    jsonschema.validate(doc, SCHEMA)
    assert doc["kind"] == kind and doc["method"] == method
    back = CalibrationModel.from_json_dict(doc)
    a, b = m.correct(model, cols), m.correct(back, cols)
    assert set(a) == set(b) and {o for o in m.outputs if not o.startswith("u_")} <= set(a)
    # spec: uncertainty columns wherever the model has a covariance
    if doc["covariance"] is not None:
        assert set(m.outputs) <= set(a)
    for k in a:
        assert np.allclose(a[k], b[k], rtol=0, atol=1e-12, equal_nan=True), k
    if kind == "stage":
        targets = {
            "target_x_deg": np.array([0.0, 5.0, -7.5]),
            "target_y_deg": np.array([0.0, -3.0, 9.0]),
        }
        la, lb = m.level(model, targets), m.level(back, targets)
        for k in ("stage_x_deg", "stage_y_deg"):
            assert np.allclose(la[k], lb[k], atol=1e-12)
