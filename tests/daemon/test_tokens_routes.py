"""POST /tokens, GET /tokens, DELETE /tokens/{name}: admin only, the token shown once, audited."""

from __future__ import annotations

import sqlalchemy as sa

from service.storage.models import AuditEvent


def test_admin_makes_lists_and_revokes_a_read_only_token(daemon) -> None:
    client, admin = daemon
    made = client.post("/tokens", headers=admin, json={"name": "lims-reader", "scopes": ["read"]})
    assert made.status_code == 201, made.text
    body = made.json()
    assert body["name"] == "lims-reader" and body["scopes"] == ["read"] and body["revoked_utc"] is None
    assert made.headers["location"] == "/tokens/lims-reader" and made.headers["cache-control"] == "no-store"
    token = body["token"]
    assert token.startswith("tl_")
    lims = {"Authorization": f"Bearer {token}"}
    # the token works for reading, not for operating nor for managing tokens
    assert client.get("/benches", headers=lims).status_code == 200
    assert client.post("/stage/stop", headers=lims, json={}).status_code == 403
    assert client.get("/tokens", headers=lims).status_code == 403
    assert client.post("/tokens", headers=lims, json={"name": "x", "scopes": ["admin"]}).status_code == 403
    # listed without its text: shown once
    listed = client.get("/tokens", headers=admin).json()["tokens"]
    row = next(t for t in listed if t["name"] == "lims-reader")
    assert "token" not in row and token not in str(listed)
    assert row["scopes"] == ["read"] and row["created_by"]
    # a second token of the same name is refused, naming the field
    again = client.post("/tokens", headers=admin, json={"name": "lims-reader", "scopes": ["read"]})
    assert again.status_code == 409 and again.json()["field"] == "name"
    # revoked: refused at once
    gone = client.delete("/tokens/lims-reader", headers=admin)
    assert gone.status_code == 200 and gone.json()["revoked_utc"] is not None
    assert client.get("/benches", headers=lims).status_code == 401
    assert all(t["name"] != "lims-reader" for t in client.get("/tokens", headers=admin).json()["tokens"])
    assert any(t["name"] == "lims-reader" and t["revoked_utc"]
               for t in client.get("/tokens?include_revoked=true", headers=admin).json()["tokens"])
    assert client.delete("/tokens/lims-reader", headers=admin).status_code == 404
    # audited, by the admin token's name
    with client.app.state.store.db.session() as s:
        actions = [(e.action, e.entity_id) for e in s.scalars(sa.select(AuditEvent).order_by(AuditEvent.id))]
    assert ("token.create", "lims-reader") in actions and ("token.revoke", "lims-reader") in actions


def test_bad_token_requests_name_the_field(daemon) -> None:
    client, admin = daemon
    for body, field in (({"name": "bad name!", "scopes": ["read"]}, "name"),
                        ({"name": "ok", "scopes": ["root"]}, "scopes"),
                        ({"name": "ok", "scopes": []}, "scopes")):
        r = client.post("/tokens", headers=admin, json=body)
        assert r.status_code == 422, (body, r.text)
        assert field in (r.json().get("field") or r.text), (body, r.text)
    assert client.get("/tokens").status_code == 401
