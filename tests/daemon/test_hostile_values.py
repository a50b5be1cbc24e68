"""Values a stranger or a careless client sends: each is answered 4xx (422 naming the field, or 404
for an id the database cannot hold), never 500, and nothing in the database changes."""

from __future__ import annotations

import json
from typing import Any

import pytest
import sqlalchemy as sa
from starlette.websockets import WebSocketDisconnect

from service.storage.feed import encode_cursor
from tests.helpers.daemon import admin_headers, make_client

GRID = {"x_deg": [-1.0, 1.0], "y_deg": [-1.0, 1.0], "n_x": 3, "n_y": 3}
JOB = {"procedure": "stage-grid", "method": "kinematic", "grid": GRID}
STANDARD = {
    "name": "reference inclinometer",
    "serial": "REF-77",
    "certificate_number": "DAkkS-2026-0412",
    "certificate_sha256": "ab" * 32,
    "calibrated_on": "2026-01-10",
    "due_on": "2099-01-10",
    "uncertainty": "0.001 deg (k = 2)",
}
ORDER = {
    "lims_order_id": "LIMS-118",
    "item_serial": "CUST-55",
    "procedure": "stage-grid",
    "method": "homography",
    "customer": {"name": "Survey Ltd", "city": "Berlin", "country_code": "DE"},
}
# past PostgreSQL's INTEGER, SQLite's INTEGER, any integer a database holds
BEYOND = [2**31, 2**63, 10**30]


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """One daemon for the module: every case leaves it as it was (that is what is tested)."""
    data = tmp_path_factory.mktemp("hostile")
    with make_client(data) as client:
        yield client, admin_headers(data)


def _rows(client: Any) -> dict[str, int]:
    engine = client.app.state.engine
    with engine.connect() as c:
        tables = [t for t in sa.inspect(c).get_table_names() if t != "alembic_version"]
        return {t: c.execute(sa.text(f"SELECT count(*) FROM {t}")).scalar() for t in tables}


def _raw(client: Any, path: str, text: str, headers: dict[str, str]) -> Any:
    """A body as a client writes it, where JSON allows what Python's json would not produce (NaN,
    Infinity)."""
    return client.post(
        path, content=text.encode(), headers={**headers, "Content-Type": "application/json"}
    )


def _refused(r: Any, status: int, field: str | None = None) -> None:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json"), r.headers
    body = r.json()
    assert body["status"] == status and body["title"] and body["detail"]
    if field is not None:
        assert body["field"] == field, body
        assert field in body["detail"], body


@pytest.mark.parametrize(
    "case",
    [
        # numbers: NaN and infinities (as JSON writers spell them), booleans
        (
            "/calibrations",
            (
                '{"procedure": "stage-grid", "method": "kinematic", "grid": {"x_deg": [NaN, '
                '1], "y_deg": [-1, 1], "n_x": 3, "n_y": 3}}'
            ),
            "grid.x_deg[0]",
        ),
        (
            "/calibrations",
            (
                '{"procedure": "stage-grid", "method": "kinematic", "grid": {"points": [[0, '
                "Infinity], "
                "[1, 1]]}}"
            ),
            "grid.points[0][1]",
        ),
        (
            "/calibrations",
            (
                '{"procedure": "stage-grid", "method": "kinematic", "grid": {"x_deg": [-1, 1], '
                '"y_deg": [-1, 1],'
                ' "n_x": 3, "n_y": 3}, "settle": {"tolerance_deg": -Infinity}}'
            ),
            "settle.tolerance_deg",
        ),
        ("/stage/move", '{"x_deg": NaN, "y_deg": 0}', "x_deg"),
        ("/stage/move", '{"x_deg": 0, "y_deg": 1e400}', "y_deg"),
        ("/stage/move", '{"x_deg": true, "y_deg": 0}', "x_deg"),
        ("/stage/level", '{"x_deg": 0, "y_deg": false}', "y_deg"),
        ("/calibrations", json.dumps({**JOB, "samples_per_point": True}), "samples_per_point"),
        ("/calibrations", json.dumps({**JOB, "grid": {**GRID, "n_x": True}}), "grid.n_x"),
        # a grid past TILTLAB_MAX_GRID_POINTS (default 10,000)
        ("/calibrations", json.dumps({**JOB, "grid": {**GRID, "n_x": 1000, "n_y": 1000}}), "grid"),
        ("/calibrations", json.dumps({**JOB, "grid": {"points": [[0.0, 0.0]] * 10_001}}), "grid"),
        # ids past the database's range in bodies
        ("/calibrations", json.dumps({**JOB, "order_id": 2**63}), "order_id"),
        (
            "/calibrations",
            json.dumps({**JOB, "reference_standards": [2**40]}),
            "reference_standards[0]",
        ),
        # unknown methods and procedures
        ("/orders", json.dumps({**ORDER, "method": "no-such-method"}), "method"),
        ("/orders", json.dumps({**ORDER, "procedure": "tumble"}), "procedure"),
        ("/calibrations", json.dumps({**JOB, "method": "no-such-method"}), "method"),
        # control characters in text
        (
            "/standards",
            json.dumps({**STANDARD, "certificate_number": "DAkkS\u00002026"}),
            "certificate_number",
        ),
        (
            "/orders",
            json.dumps({**ORDER, "customer": {**ORDER["customer"], "name": "Survey\u0000Ltd"}}),
            "customer.name",
        ),
        ("/orders", json.dumps({**ORDER, "lims_order_id": "L\u001b[2J"}), "lims_order_id"),
        ("/calibrations", json.dumps({**JOB, "note": "a\u0000b"}), "note"),
        ("/records/1/reject", json.dumps({"reason": "\u0007"}), "reason"),
        ("/webhooks", json.dumps({"url": "http://127.0.0.1:9/\u0000", "events": ["*"]}), "url"),
        # bidirectional overrides and isolates: text that shows in another order than it was typed
        (
            "/orders",
            json.dumps({**ORDER, "customer": {**ORDER["customer"], "name": "Survey \u202eLtd"}}),
            "customer.name",
        ),
        ("/standards", json.dumps({**STANDARD, "serial": "AC-\u2067 77"}), "serial"),
        ("/calibrations", json.dumps({**JOB, "note": "passed \u202d(failed)\u202c"}), "note"),
        ("/records/1/approve", json.dumps({"note": "ok\u2066"}), "note"),
        # a webhook URL with credentials would be stored and shown to every admin
        (
            "/webhooks",
            json.dumps({"url": "https://lims:secret@lims.example.org/hook", "events": ["*"]}),
            "url",
        ),
        ("/webhooks", json.dumps({"url": "gopher://127.0.0.1:9/", "events": ["*"]}), "url"),
        (
            "/webhooks",
            json.dumps({"url": "http://127.0.0.1:9/", "events": ["record.exploded"]}),
            "events[0]",
        ),
    ],
    ids=lambda c: c[2] if isinstance(c, tuple) else str(c),
)
def test_hostile_bodies_are_422_naming_the_field_and_change_nothing(
    daemon: Any, case: tuple[str, str, str]
) -> None:
    client, h = daemon
    path, text, field = case
    pose = client.app.state.bench.sim.world.pose_deg
    before = _rows(client)
    _refused(_raw(client, path, text, h), 422, field)
    assert _rows(client) == before
    assert client.app.state.bench.sim.world.pose_deg == pose


def test_ids_beyond_the_database_are_404_or_422_never_500(daemon: Any) -> None:
    client, h = daemon
    before = _rows(client)
    for n in BEYOND:
        for path in (
            f"/calibrations/{n}",
            f"/records/{n}",
            f"/records/{n}/model",
            f"/records/{n}/points",
            f"/records/{n}/residuals",
            f"/records/{n}/approvals",
            f"/records/{n}/certificate",
            f"/records/{n}/certificate.html",
            f"/standards/{n}",
            f"/orders/{n}",
            f"/webhooks/{n}/deliveries",
        ):
            _refused(client.get(path, headers=h), 404)
        for path in (
            f"/calibrations/{n}/cancel",
            f"/calibrations/{n}/resume",
            f"/records/{n}/activate",
        ):
            _refused(client.post(path, headers=h), 404)
        _refused(client.post(f"/records/{n}/approve", json={}, headers=h), 404)
        _refused(client.get("/records", params={"device": n}, headers=h), 422, "device")
        _refused(client.get("/calibrations", params={"cursor": n}, headers=h), 422, "cursor")
    _refused(client.get("/feed", params={"cursor": encode_cursor(2**70)}, headers=h), 422, "cursor")
    _refused(client.get("/feed", params={"cursor": "f1.not-base64!"}, headers=h), 422, "cursor")
    assert _rows(client) == before


@pytest.mark.parametrize("job_id", ["9" * 400, "\u0661\u0662", "\u00b2", "12%00", "-1", "0"])
def test_job_stream_handshake_with_a_hostile_id_is_refused(daemon: Any, job_id: str) -> None:
    client, h = daemon
    token = h["Authorization"].split()[1]
    with (
        client.websocket_connect(f"/ws/jobs/{job_id}?token={token}") as ws,
        pytest.raises(WebSocketDisconnect) as closed,
    ):
        ws.receive_text()
    assert closed.value.code == 1008 and closed.value.reason.startswith("id:"), closed.value
