"""Every request whose fit cannot succeed is refused at POST /calibrations (422 naming the field),
before the bench moves: nothing is stored, the stage stands where it stood, and the bench is free
for the next."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import sqlalchemy as sa
from hypothesis import given, settings
from hypothesis import strategies as st

from service.jobs.requests import CalibrationRequest
from service.jobs.stage_grid import STAGE_GRID
from tests.helpers.daemon import admin_headers, make_client

GRID = {"x_deg": [-2.0, 2.0], "y_deg": [-2.0, 2.0], "n_x": 3, "n_y": 3}
TABLES = (
    "calibration_jobs",
    "settled_points",
    "samples",
    "calibration_records",
    "idempotency_keys",
)


@pytest.fixture(scope="module")
def daemon(tmp_path_factory) -> Iterator[tuple]:
    data = tmp_path_factory.mktemp("data")
    with make_client(data) as client:
        yield client, admin_headers(data)


def _counts(client) -> dict[str, int]:
    with client.app.state.engine.connect() as c:
        return {t: c.execute(sa.text(f"SELECT count(*) FROM {t}")).scalar() for t in TABLES}


def refused(daemon, field: str, words: str, *, method: str = "kinematic", **grid) -> str:
    """POST /calibrations with this grid: 422 naming `field`, the detail saying `words`, nothing
    stored or moved."""
    client, h = daemon
    before = _counts(client)
    pose = client.app.state.bench.sim.world.pose_deg
    body = {
        "procedure": "stage-grid",
        "method": method,
        "grid": grid,
        "validation": {"n_points": 2},
    }
    r = client.post("/calibrations", headers=h, json=body)
    assert r.status_code == 422, r.text
    problem = r.json()
    assert problem["field"] == field, problem
    assert words in problem["detail"], problem
    assert _counts(client) == before
    assert client.app.state.bench.sim.world.pose_deg == pose
    assert client.app.state.bench.holder is None  # the bench is free for a usable request
    return str(problem["detail"])


def test_an_empty_x_range_is_refused(daemon):
    detail = refused(daemon, "grid.x_deg", "empty range", **{**GRID, "x_deg": [2, 2]})
    assert "upper stage" in detail


def test_an_empty_y_range_is_refused(daemon):
    detail = refused(daemon, "grid.y_deg", "empty range", **{**GRID, "y_deg": [-1.5, -1.5]})
    assert "lower stage" in detail


def test_one_x_position_is_refused(daemon):
    refused(daemon, "grid.n_x", "two or more angles", **{**GRID, "n_x": 1, "n_y": 9})


def test_one_y_position_is_refused(daemon):
    refused(daemon, "grid.n_y", "two or more angles", **{**GRID, "n_x": 9, "n_y": 1})


def test_points_with_one_stage_standing_are_refused(daemon):
    refused(
        daemon, "grid.points", "upper stage (x) at 1 deg", points=[[1, y] for y in range(-3, 4)]
    )


@pytest.mark.parametrize(
    ("method", "need"), [("kinematic", 6), ("homography", 5), ("axis-transform", 4)]
)
def test_too_few_points_for_the_method_are_refused(daemon, method, need):
    corners = [[-2, -2], [2, -2], [-2, 2], [2, 2], [0, 2], [2, 0]][: need - 1]
    refused(
        daemon, "grid", f"the {method} fit needs at least {need}", method=method, points=corners
    )


def test_repeated_points_count_once(daemon):
    points = [[-2, -2], [2, -2], [-2, 2], [2, 2]] * 3  # 12 points, 4 places
    refused(daemon, "grid", "4 distinct points (8 repeated)", points=points)


def test_coupling_without_a_point_off_the_axes_is_refused(daemon):
    cross = [[0, -2], [0, -1], [0, 1], [0, 2], [-2, 0], [-1, 0], [1, 0], [2, 0]]
    refused(daemon, "grid", "both stages tilted", method="coupling", points=cross)


def test_a_grid_the_kinematic_fit_cannot_separate_is_refused(daemon):
    """A 3 x 3 grid a hundredth of a degree wide: the stages' scales and tilts do not show over
    it."""
    detail = refused(
        daemon,
        "grid",
        "do not separate",
        **{**GRID, "x_deg": [-0.01, 0.01], "y_deg": [-0.01, 0.01]},
    )
    assert "before measuring" in detail


def test_the_same_grids_made_usable_are_taken(daemon):
    """The refusals are of the geometry, not of the bench: a usable grid right after is admitted."""
    client, h = daemon
    bench = client.app.state.bench
    for method in ("kinematic", "homography", "axis-transform", "coupling"):
        plan = STAGE_GRID.plan(
            CalibrationRequest(procedure="stage-grid", method=method, grid=GRID), bench
        )
        assert len(plan.fit_points) == 9


@settings(max_examples=40, deadline=None)
@given(
    x0=st.floats(-10, 10),
    dx=st.floats(0.5, 5),
    y0=st.floats(-10, 10),
    dy=st.floats(0.5, 5),
    n_x=st.integers(2, 6),
    n_y=st.integers(3, 6),
    n_val=st.integers(0, 12),
)
def test_validation_points_lie_inside_the_calibrated_range(daemon, x0, dx, y0, dy, n_x, n_y, n_val):
    """Validation points are drawn inside the range the fit points span, so the record is judged
    where it holds."""
    client, _ = daemon
    grid = {"x_deg": [x0, x0 + dx], "y_deg": [y0, y0 + dy], "n_x": n_x, "n_y": n_y}
    req = CalibrationRequest(
        procedure="stage-grid", method="homography", grid=grid, validation={"n_points": n_val}
    )
    plan = STAGE_GRID.plan(req, client.app.state.bench)
    assert len(plan.validation_points) == n_val
    for vx, vy in plan.validation_points:
        assert x0 - 1e-4 <= vx <= x0 + dx + 1e-4 and y0 - 1e-4 <= vy <= y0 + dy + 1e-4, (
            vx,
            vy,
            grid,
        )
