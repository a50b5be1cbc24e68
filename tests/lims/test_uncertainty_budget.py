"""The uncertainty budget of a result (GUM): the fit, the reference standard, the sensors'
resolution and the temperature's influence; checked against GTC, an independent GUM tool, and end to
end on the daemon."""

from __future__ import annotations

import datetime as dt
import math

import numpy as np
import pytest
from GTC import dof as gtc_dof
from GTC import reporting, uncertainty, ureal

from service.bench.corrected import corrected_tilt
from service.calibration.budget import (
    combine,
    record_budget,
    standard_component,
    temperature_component,
)
from service.calibration.model import CalibrationModel
from service.calibration.registry import get_method
from service.calibration.uncertainty import coverage_factor, dof_of_coverage_factor
from service.instruments.base import Reading
from service.io.columns import K_OUTPUTS
from service.jobs.manager import ActiveModel
from tests.helpers.certificates import _stage_fit
from tests.helpers.lims import PEOPLE

STANDARD = {
    "name": "reference inclinometer",
    "serial": "REF-77",
    "certificate_id": "DAkkS-2026-0412",
    "expanded_uncertainty_deg": 0.02,
    "coverage_factor": 2.0,
}


def _budget(model: CalibrationModel, rng: np.random.Generator) -> dict:
    temps = 20.0 + rng.uniform(0.0, 1.5, 40)
    errors = np.column_stack([3e-4 * (temps - 20.7), -1e-4 * (temps - 20.7)]) + rng.normal(
        0, 2e-5, (40, 2)
    )
    return record_budget(
        parameters=model.to_json_dict()["parameters"],
        parameter_u={n: s for n in model.parameters if (s := model.std(n)) is not None},
        dof_fit=60.0,
        standards=[STANDARD],
        resolutions_deg={"measurement sensor": 1e-4, "reference sensor": 1e-4},
        tilt_u_fit_deg=(1e-3, 1.2e-3),
        tilt_dof_fit=(40.0, 40.0),
        temps_c=temps,
        errors_deg=errors,
    )


@pytest.mark.parametrize("method", ["kinematic", "homography"])
def test_tilt_uncertainty_agrees_with_gtc(method: str) -> None:
    model = CalibrationModel.from_json_dict(_stage_fit(method, 3)[0])
    m = get_method("stage", method)
    budget = _budget(model, np.random.default_rng(11))
    sources = [c["source"] for c in budget["components"]]
    assert sources == ["reference_standard", "resolution", "resolution", "temperature"], sources
    active = ActiveModel(1, 1, method, model, m, budget)
    for x, y in [(0.3, -0.2), (1.7, 1.1), (-1.9, 0.8)]:
        reading = Reading("measurement_sensor", 0.0, dt.datetime.now(dt.UTC), x_deg=x, y_deg=y)
        got = corrected_tilt(active, reading)
        fit = m.correct(model, {"meas_x_deg": np.array([x]), "meas_y_deg": np.array([y])})
        for axis, key, k_out in (("x", "u_x_deg", "k"), ("y", "u_y_deg", "k_y")):
            k_fit = float(fit[K_OUTPUTS[0 if axis == "x" else 1]][0])
            u_fit = float(fit[f"u_tilt_{axis}_deg"][0]) / k_fit
            # GTC: one uncertain number per component, summed with unit sensitivities
            total = ureal(0.0, u_fit, df=float(dof_of_coverage_factor(k_fit)))
            for c in budget["components"]:
                total = total + ureal(
                    0.0, c["u_deg"], df=math.inf if c["dof"] is None else c["dof"]
                )
            k_gtc = reporting.k_factor(gtc_dof(total), 95)
            assert got[k_out] == pytest.approx(k_gtc, rel=1e-6)
            assert got[key] == pytest.approx(k_gtc * uncertainty(total), rel=1e-6)
            # the budget adds to the fit's part
            assert got[key] > float(fit[f"u_tilt_{axis}_deg"][0])


def test_the_standards_stated_k_gives_its_degrees_of_freedom_and_its_U_passes_on() -> None:
    c = standard_component("std", 0.02, 2.0)
    assert c.u_deg == 0.01 and float(coverage_factor(c.dof)) == pytest.approx(2.0, rel=1e-9)
    alone = combine(np.array([1e-4]), np.array([50.0]), [c])
    assert alone.U[0] >= 0.02
    assert math.isinf(standard_component("std", 0.02, 1.9).dof)  # below the normal's k: no finite ν
    for k, nu in ((2.2281388519649385, 10.0), (3.182446305284263, 3.0)):
        assert float(dof_of_coverage_factor(k)) == pytest.approx(nu, rel=1e-9)
        assert reporting.k_factor(nu, 95) == pytest.approx(float(coverage_factor(nu)), rel=1e-9)


def test_temperature_influence_only_where_it_varied() -> None:
    rng = np.random.default_rng(5)
    steady = 21.3 + rng.normal(0, 0.005, 30)
    comp, stats = temperature_component(steady, rng.normal(0, 1e-4, 30))
    assert comp is None and stats["span_c"] < 0.05
    t = np.linspace(19.0, 23.0, 30)
    comp, stats = temperature_component(t, 5e-4 * (t - 21.0) + rng.normal(0, 1e-5, 30))
    assert comp is not None and stats["coefficient_deg_per_c"] == pytest.approx(5e-4, rel=0.05)
    assert comp.u_deg == pytest.approx(5e-4 * 4.0 / math.sqrt(12), rel=0.05)


def test_the_budget_names_each_result_and_the_zero_offsets_carry_the_standard() -> None:
    model = CalibrationModel.from_json_dict(_stage_fit("kinematic", 3)[0])
    budget = _budget(model, np.random.default_rng(2))
    results = {r["quantity"]: r for r in budget["results"]}
    assert {"tilt_x_deg", "tilt_y_deg", "zero_offset.meas_x_deg", "zero_offset.meas_y_deg"} <= set(
        results
    )
    assert "scale_factor.meas_x" not in results  # a scale carries no angle offset of the standard
    zero = results["zero_offset.meas_x_deg"]
    assert [c["source"] for c in zero["contributions"]] == ["fit", "reference_standard"]
    assert zero["standard_uncertainty"] == pytest.approx(
        math.hypot(model.std("zero_offset.meas_x_deg"), 0.01), rel=1e-12
    )
    tilt = results["tilt_x_deg"]
    assert tilt["standard_uncertainty"] == pytest.approx(
        math.sqrt(sum(c["standard_uncertainty"] ** 2 for c in tilt["contributions"])), rel=1e-12
    )
    assert tilt["expanded_uncertainty"] == pytest.approx(
        tilt["coverage_factor"] * tilt["standard_uncertainty"], rel=1e-12
    )
    assert tilt["expanded_uncertainty"] >= 0.02
    # no two keys differ only by case (some JSON mappers ignore case)
    for entry in (tilt, *tilt["contributions"]):
        assert len({k.lower() for k in entry}) == len(entry), entry


def test_a_standard_of_U_0_02_deg_reaches_tilt_and_the_record_through_the_daemon(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from tests.helpers.daemon import fresh_tilt, make_client, wait_job
    from tests.helpers.lims import GRID, LAB

    with make_client(tmp_path, **LAB) as client:
        store = client.app.state.store
        h = {
            n: {"Authorization": f"Bearer {token}"}
            for n in ("alice", "bob")
            for token in [store.tokens.create_token(n, "admin", actor="setup", person=PEOPLE[n])[1]]
        }
        std = client.post(
            "/standards",
            headers=h["alice"],
            json={
                "name": "autocollimator",
                "serial": "AC-7",
                "certificate_number": "DAkkS-2026-7",
                "certificate_sha256": "ab" * 32,
                "calibrated_on": "2026-01-10",
                "due_on": "2099-01-10",
                "expanded_uncertainty_deg": 0.02,
                "coverage_factor": 2,
                "calibrated_by": {"name": "Angle Calibration Laboratory AG", "country_code": "DE"},
            },
        )
        assert std.status_code == 201 and std.json()["expanded_uncertainty_deg"] == 0.02, std.text
        vague = client.post(
            "/standards",
            headers=h["alice"],
            json={
                "name": "old level",
                "serial": "L-1",
                "certificate_number": "C-1",
                "certificate_sha256": "cd" * 32,
                "calibrated_on": "2026-01-10",
                "due_on": "2099-01-10",
                "uncertainty": "see the certificate",
            },
        ).json()
        assert vague["expanded_uncertainty_deg"] is None
        body = {
            "procedure": "stage-grid",
            "method": "homography",
            "grid": GRID,
            "samples_per_point": 8,
            "validation": {"n_points": 3},
            "settle": {"tolerance_deg": 0.002, "window_s": 2.0, "timeout_s": 600.0},
        }
        r = client.post(
            "/calibrations",
            headers=h["alice"],
            json={**body, "reference_standards": [std.json()["id"], vague["id"]]},
        )
        assert (
            r.status_code == 422
            and r.json()["field"] == "reference_standards[1]"
            and "old level" in r.text
        ), r.text
        r = client.post(
            "/calibrations",
            headers=h["alice"],
            json={**body, "reference_standards": [std.json()["id"]]},
        )
        assert r.status_code == 202, r.text
        job = wait_job(client, r.json()["id"], h["alice"])
        assert job["state"] == "succeeded", job
        rid = job["record"]["id"]
        record = client.get(f"/records/{rid}", headers=h["alice"]).json()
        budget = record["budget"]
        named = [c for c in budget["components"] if c["source"] == "reference_standard"]
        assert (
            len(named) == 1
            and "autocollimator" in named[0]["name"]
            and named[0]["u_deg"] == pytest.approx(0.01)
        )
        assert {c["name"] for c in budget["components"] if c["source"] == "resolution"} == {
            "measurement sensor resolution",
            "reference sensor resolution",
        }
        tilt_x = next(r for r in budget["results"] if r["quantity"] == "tilt_x_deg")
        assert tilt_x["expanded_uncertainty"] >= 0.02
        assert client.post(f"/records/{rid}/activate", headers=h["alice"]).status_code == 200
        t = fresh_tilt(client, h["alice"])["table_tilt"]
        assert t["u_x_deg"] >= 0.02 and t["u_y_deg"] >= 0.02, t
        # the certificate states the budget, naming the standard, and the zero offsets' U carries it
        assert (
            client.post(
                f"/records/{rid}/approve", json={"meaning": "approval"}, headers=h["bob"]
            ).status_code
            == 200
        )
        xml = client.get(f"/records/{rid}/certificate", headers=h["bob"]).content.decode()
        budget_part = xml[xml.index("Uncertainty budget") :]
        assert "autocollimator (serial AC-7, certificate DAkkS-2026-7)" in budget_part
        assert "measurement sensor resolution" in budget_part


def test_a_budget_stored_under_the_former_names_is_read_under_the_present_ones() -> None:
    from service.calibration.budget import current_names

    stored = {
        "components": [],
        "results": [
            {
                "quantity": "tilt_x_deg",
                "u": 0.001,
                "U": 0.002,
                "k": 2.0,
                "dof_eff": None,
                "contributions": [{"source": "fit", "u": 0.001}],
            }
        ],
    }
    (r,) = current_names(stored)["results"]
    assert (r["standard_uncertainty"], r["expanded_uncertainty"], r["coverage_factor"]) == (
        0.001,
        0.002,
        2.0,
    )
    assert (
        "u" not in r
        and "U" not in r
        and r["contributions"] == [{"source": "fit", "standard_uncertainty": 0.001}]
    )
    assert stored["results"][0]["U"] == 0.002  # the stored budget itself is left as it was
