"""Repeated fits of one simulated bench agree within what each states: a parameter the points do not
determine is not stated as if they did (the kinematic chain's near-degenerate pairs,
docs/calibration-stage.md)."""

import numpy as np
import pytest
from scipy import stats

from service.calibration.registry import FitOptions, get_method
from service.scenarios import load_scenario, parse_scenario, run_scenario

N_FITS = 10


def _bench(grid):
    data = load_scenario("seed000").model_dump(mode="json", exclude_defaults=True)
    data["grid"].update(grid)
    return parse_scenario(data)


# the daemon's resume test calibrates a 3 x 3 grid at ±2 deg from the means of 6 readings per point;
# seed 000's is 9 x 9
DAEMON_GRID = {"x_deg": [-2.0, 0.0, 2.0], "y_deg": [-2.0, 0.0, 2.0], "readings_per_stand": 6}


@pytest.fixture(scope="module", params=["seed000 grid", "daemon grid"])
def fits(request):
    grid = {} if request.param == "seed000 grid" else DAEMON_GRID
    per = grid.get("readings_per_stand", 1)
    sc = _bench(grid)
    m = get_method("stage", "kinematic")
    out = []
    for seed in range(500, 500 + N_FITS):
        cols = run_scenario(sc, seed=seed).columns
        if per > 1:  # the point means, as the daemon records them
            cols = {
                k: (v[::per] if k == "point" else v.reshape(-1, per).mean(axis=1))
                for k, v in cols.items()
            }
        out.append(m.fit(cols, FitOptions()))
    return request.param, out


def test_every_parameter_lies_within_three_of_its_stated_uncertainties_of_the_fits_mean(fits):
    """Ten fits, ten noise seeds: |value - mean of the ten| <= 3 u, u the fit's own standard
    uncertainty (widened by Student's t where the fit has few degrees of freedom: 3 u is then t_ν at
    the same two-sided probability)."""
    grid, models = fits
    names = [n for n in models[0].covariance_names if not models[0].parameters[n].fixed]
    assert all(
        [n for n in m.covariance_names if not m.parameters[n].fixed] == names for m in models
    )
    values = np.array([[m.value(n) for n in names] for m in models])
    u = np.array([np.sqrt(np.diag(m.cov_of(names))) for m in models])
    dof = np.array(
        [
            [min(m.fit["chain"]["dof"], m.fit.get("meas", {}).get("covariance_dof") or np.inf)]
            * len(names)
            for m in models
        ]
    )
    widen = stats.t.ppf(stats.norm.cdf(3.0), dof) / 3.0
    z = np.abs(values - values.mean(axis=0)) / (u * widen)
    worst = int(np.argmax(z.max(axis=0)))
    assert z.max() <= 3.0, (grid, names[worst], values[:, worst], u[:, worst])
    # and the ten values spread as the stated u says, not far less (a u inflated to pass) for the
    # well-determined
    spread = values.std(axis=0, ddof=1) / np.median(u, axis=0)
    prior = {n for n in names if any(n in note and "prior" in note for note in models[0].notes)}
    for n, s in zip(names, spread):
        if n not in prior:
            assert s > 0.4, (grid, n, s)


def test_a_parameter_the_points_leave_open_is_stated_with_the_drawings_prior(fits):
    """On the daemon's small grid the lower stage's pitch is near-degenerate with its scale: its
    value and u are the drawings' prior updated by the points, and the record says so; on seed 000's
    grid nothing needs one."""
    grid, models = fits
    notes = " ".join(models[0].notes)
    if grid == "daemon grid":
        assert "axis_misalignment.lower_pitch_deg" in notes and "prior 0 ± 0.5 deg" in notes
        u = [np.sqrt(m.cov_of(["axis_misalignment.lower_pitch_deg"])[0, 0]) for m in models]
        assert all(0.3 < x <= 0.5 for x in u)
    else:
        assert "prior" not in notes
