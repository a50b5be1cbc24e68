"""Real calibration records for certificate tests: fitted by the calibration code on simulated data,
validated on a second simulated run (points the fit never saw)."""

from __future__ import annotations

import datetime as dt
from functools import lru_cache
from typing import Any

import numpy as np

from service.calibration.registry import FitOptions, get_method
from service.lims.as_found import MeasuredPoint
from service.lims.content import Approval, Laboratory
from service.scenarios import load_scenario
from service.scenarios.run import run_scenario
from service.storage.tokens import Person

LAB = Laboratory(
    name="Inclination Laboratory Example GmbH",
    city="Braunschweig",
    country_code="DE",
    street="Bundesallee 100",
    post_code="38116",
    accreditation="D-K-00000-01-00",
)
CUSTOMER = {"name": "Customer Survey Instruments Ltd", "city": "Berlin", "country_code": "DE"}
CALIBRATED_BY = {
    "name": "Angle Calibration Laboratory AG",
    "accreditation": "D-K-12345-01-00",
    "city": "Hamburg",
    "country_code": "DE",
}
STANDARDS = [
    {
        "name": "reference inclinometer",
        "serial": "REF-77",
        "certificate_number": "DAkkS-2026-0412",
        "certificate_sha256": "ab" * 32,
        "calibrated_on": "2026-01-10",
        "due_on": "2027-01-10",
        "uncertainty": "0.001 deg (k = 2)",
        "expanded_uncertainty_deg": 0.001,
        "coverage_factor": 2.0,
        "calibrated_by": CALIBRATED_BY,
    },
    {
        "name": "thermometer",
        "serial": "TH-3",
        "certificate_number": "DAkkS-2026-0099",
        "certificate_sha256": "cd" * 32,
        "calibrated_on": "2026-03-01",
        "due_on": "2027-03-01",
        "uncertainty": "0.1 degC (k = 2)",
        "calibrated_by": {"name": "Thermometry Lab GmbH", "country_code": "DE"},
    },
]


@lru_cache(maxsize=8)
def _stage_fit(method: str, seed: int) -> tuple[dict[str, Any], dict[str, Any]]:
    scenario = load_scenario("seed000")
    fit_run, check_run = run_scenario(scenario, seed=seed), run_scenario(scenario, seed=seed + 1)
    m = get_method("stage", method)
    model = m.fit(fit_run.columns, FitOptions())
    idx = np.arange(0, len(check_run.columns["ref_x_deg"]), 9)  # nine validation points
    cols = {k: np.asarray(v)[idx] for k, v in check_run.columns.items()}
    out = m.correct(model, cols)
    points = [
        {
            "reference_x_deg": float(cols["ref_x_deg"][i]),
            "reference_y_deg": float(cols["ref_y_deg"][i]),
            "measured_x_deg": float(out["tilt_x_deg"][i]),
            "measured_y_deg": float(out["tilt_y_deg"][i]),
            "u_x_deg": float(out["u_tilt_x_deg"][i]),
            "u_y_deg": float(out["u_tilt_y_deg"][i]),
        }
        for i in range(len(idx))
    ]
    err = np.array(
        [
            [p["measured_x_deg"] - p["reference_x_deg"], p["measured_y_deg"] - p["reference_y_deg"]]
            for p in points
        ]
    )
    validation = {
        "n_points": len(points),
        "rms_deg": float(np.sqrt(np.mean(err**2))),
        "max_deg": float(np.max(np.abs(err))),
        "points": points,
    }
    return model.to_json_dict(), validation


@lru_cache(maxsize=8)
def stage_points(seed: int = 3, readings_per_point: int = 10) -> tuple[MeasuredPoint, ...]:
    """The points of a simulated stage job: the fit run's points, then nine validation points of a
    second run, each sensor's spread per reading as the scenario simulates it (its noise sigma)."""
    scenario = load_scenario("seed000")
    noise = scenario.effects.noise
    assert noise is not None
    fit_run, check_run = run_scenario(scenario, seed=seed), run_scenario(scenario, seed=seed + 1)
    out = []
    for fitted, cols, rows in (
        (True, fit_run.columns, range(len(fit_run.columns["ref_x_deg"]))),
        (False, check_run.columns, range(0, len(check_run.columns["ref_x_deg"]), 9)),
    ):
        for i in rows:
            out.append(
                MeasuredPoint(
                    len(out),
                    fitted,
                    (float(cols["ref_x_deg"][i]), float(cols["ref_y_deg"][i])),
                    (float(cols["meas_x_deg"][i]), float(cols["meas_y_deg"][i])),
                    (noise.ref_sigma_deg, noise.ref_sigma_deg),
                    (noise.meas_sigma_deg, noise.meas_sigma_deg),
                    readings_per_point,
                    readings_per_point,
                )
            )
    return tuple(out)


CONDITIONS = {
    "resolution_deg": {"reference_sensor": 0.0001, "measurement_sensor": 0.0001},
    "samples_per_point": 10,
    "ambient_temperature_c": {"value": 20.3, "standard_uncertainty": 0.1, "source": "request"},
    "relative_humidity_pct": {"value": 45.0, "standard_uncertainty": 2.0, "source": "request"},
}


def stage_record(
    method: str = "homography", *, record_id: int = 7, version: int = 1, seed: int = 3
) -> dict[str, Any]:
    model, validation = _stage_fit(method, seed)
    return {
        "id": record_id,
        "version": version,
        "kind": "stage",
        "method": method,
        "model": model,
        "validation": validation,
        "temp_c": 20.4,
        "content_sha256": f"{record_id:064x}",
        "created_at": dt.datetime(2026, 11, 20, 15, 30, tzinfo=dt.UTC),
        "conditions": CONDITIONS,
    }


def scale_record(record_id: int = 9) -> dict[str, Any]:
    run = run_scenario(load_scenario("seed003"), seed=5)
    model = get_method("scale", "poly3").fit(run.columns, FitOptions())
    return {
        "id": record_id,
        "version": 1,
        "kind": "scale",
        "method": "poly3",
        "model": model.to_json_dict(),
        "validation": {},
        "temp_c": None,
        "content_sha256": f"{record_id:064x}",
        "created_at": dt.datetime(2026, 11, 21, 9, 0, tzinfo=dt.UTC),
    }


DEVICE = {
    "model": "SCA126T",
    "serial": "SN-4711",
    "firmware": "2.3.1",
    "manufacturer": "Example Sensors",
}
APPROVER = Person("Dr. Erika Mustermann", "Head of Laboratory")
APPROVAL = Approval(
    actor="erika",
    at=dt.datetime(2026, 11, 22, 10, 0, tzinfo=dt.UTC),
    meaning="approval",
    record_sha256="7" * 64,
    event_sha256="e" * 64,
    note="reviewed",
    signer=APPROVER,
)
OPERATOR = Person("Max Muster", "Calibration Technician")
