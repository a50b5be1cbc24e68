"""GET /tilt answered in front of the routing table: the same answer, headers and metrics as the
route's, and a revoked token refused at once."""

from __future__ import annotations

from service.api.prepared_tilt import PreparedTilt


def _keys(body: dict) -> set[str]:
    return set(body)


def test_the_prepared_answer_is_the_routes(daemon, monkeypatch) -> None:
    client, admin = daemon
    # the first asks the database for the token: the full path
    routed = client.get("/tilt", headers=admin)
    answered: list[bool] = []  # per call: did the prepared path answer (True) or pass it on (False)
    answer = PreparedTilt._answer

    def watched(self, scope):
        body = answer(self, scope)
        answered.append(body is not None)
        return body

    monkeypatch.setattr(PreparedTilt, "_answer", watched)
    prepared = client.get("/tilt", headers=admin)
    assert answered == [True] and routed.status_code == prepared.status_code == 200
    assert _keys(routed.json()) == _keys(prepared.json())
    assert routed.json()["bench"] == prepared.json()["bench"]
    assert prepared.headers["content-type"] == routed.headers["content-type"] == "application/json"
    assert int(prepared.headers["content-length"]) == len(prepared.content)
    bench = prepared.json()["bench"]
    assert client.get(f"/tilt?bench={bench}", headers=admin).json()["bench"] == bench
    # the route's own answer
    assert client.get("/tilt?bench=nowhere", headers=admin).status_code == 404
    assert client.head("/tilt", headers=admin).status_code == 200
    # HEAD is counted as the GET it is answered as
    metrics = client.get("/metrics", headers=admin).text
    assert 'tiltlab_http_requests_total{method="GET",route="/tilt",status="200"} 4.0' in metrics


def test_a_revoked_token_is_refused_at_once(daemon) -> None:
    client, admin = daemon
    token = client.post(
        "/tokens", headers=admin, json={"name": "poller", "scopes": ["read"]}
    ).json()["token"]
    reader = {"Authorization": f"Bearer {token}"}
    assert client.get("/tilt", headers=reader).status_code == 200
    assert client.get("/tilt", headers=reader).status_code == 200  # known now: the prepared path
    assert client.delete("/tokens/poller", headers=admin).status_code == 200
    assert client.get("/tilt", headers=reader).status_code == 401
    assert client.get("/tilt").status_code == 401
    assert client.get("/tilt", headers={"Authorization": "Bearer tl_unknown"}).status_code == 401
