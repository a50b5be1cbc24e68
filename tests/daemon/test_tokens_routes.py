"""POST /tokens, GET /tokens, DELETE /tokens/{name}: admin only, the token shown once, audited."""

from __future__ import annotations

import sqlalchemy as sa

from service.storage.models import AuditEvent


def test_admin_makes_lists_and_revokes_a_read_only_token(daemon) -> None:
    client, admin = daemon
    made = client.post("/tokens", headers=admin, json={"name": "lims-reader", "scopes": ["read"]})
    assert made.status_code == 201, made.text
    body = made.json()
    assert (
        body["name"] == "lims-reader" and body["scopes"] == ["read"] and body["revoked_utc"] is None
    )
    assert (
        made.headers["location"] == "/tokens/lims-reader"
        and made.headers["cache-control"] == "no-store"
    )
    token = body["token"]
    assert token.startswith("tl_")
    lims = {"Authorization": f"Bearer {token}"}
    # the token works for reading, not for operating nor for managing tokens
    assert client.get("/benches", headers=lims).status_code == 200
    assert client.post("/stage/stop", headers=lims, json={}).status_code == 403
    assert client.get("/tokens", headers=lims).status_code == 403
    assert (
        client.post("/tokens", headers=lims, json={"name": "x", "scopes": ["admin"]}).status_code
        == 403
    )
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
    assert all(
        t["name"] != "lims-reader" for t in client.get("/tokens", headers=admin).json()["tokens"]
    )
    assert any(
        t["name"] == "lims-reader" and t["revoked_utc"]
        for t in client.get("/tokens?include_revoked=true", headers=admin).json()["tokens"]
    )
    assert client.delete("/tokens/lims-reader", headers=admin).status_code == 404
    # audited, by the admin token's name
    with client.app.state.store.db.session() as s:
        actions = [
            (e.action, e.entity_id)
            for e in s.scalars(sa.select(AuditEvent).order_by(AuditEvent.id))
        ]
    assert ("token.create", "lims-reader") in actions and ("token.revoke", "lims-reader") in actions


def test_bad_token_requests_name_the_field(daemon) -> None:
    client, admin = daemon
    for body, field in (
        ({"name": "bad name!", "scopes": ["read"]}, "name"),
        ({"name": "ok", "scopes": ["root"]}, "scopes"),
        ({"name": "ok", "scopes": []}, "scopes"),
    ):
        r = client.post("/tokens", headers=admin, json=body)
        assert r.status_code == 422, (body, r.text)
        assert field in (r.json().get("field") or r.text), (body, r.text)
    assert client.get("/tokens").status_code == 401


def test_a_token_names_its_person_who_alone_may_sign(daemon, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The person behind a token: set when it is made or later (PATCH), shown, audited; approving
    needs one with a function (403 naming what is missing)."""
    client, admin = daemon
    store = client.app.state.store
    person = {"name": "Dr. Alice Example", "function": "Head of Laboratory"}
    made = client.post(
        "/tokens", headers=admin, json={"name": "alice", "scopes": ["admin"], "person": person}
    )
    assert made.status_code == 201 and made.json()["person"] == person, made.text
    nameless = client.post(
        "/tokens",
        headers=admin,
        json={"name": "bob", "scopes": ["admin"], "person": {"name": "Bob Example"}},
    ).json()
    assert nameless["person"] == {"name": "Bob Example", "function": None}
    listed = {t["name"]: t["person"] for t in client.get("/tokens", headers=admin).json()["tokens"]}
    # the first admin token names none until given one
    assert listed["alice"] == person and listed["admin"] is None
    # bad persons are refused naming the field
    for bad, field in (
        ({"function": "x"}, "person.name"),
        ({"name": " "}, "person.name"),
        ({"name": "A", "function": "x" * 201}, "person.function"),
    ):
        r = client.post(
            "/tokens", headers=admin, json={"name": "carol", "scopes": ["read"], "person": bad}
        )
        assert r.status_code == 422 and field in (r.json().get("field") or "") + r.text, (
            bad,
            r.text,
        )
    # a record to sign: started by the admin token, signed by others
    meas = client.app.state.bench.device_ids["measurement_sensor"]
    job = store.jobs.create_job(meas, "stage", "kinematic", actor="admin")
    store.jobs.start_job(job.id, actor="daemon")
    from tests.helpers.certificates import stage_record

    record = store.records.add_record(
        meas,
        "stage",
        "kinematic",
        stage_record("kinematic")["model"],
        operator="admin",
        job_id=job.id,
    )
    bob = {"Authorization": f"Bearer {nameless['token']}"}
    r = client.post(f"/records/{record.id}/approve", headers=bob, json={"meaning": "approval"})
    assert (
        r.status_code == 403
        and "not their function" in r.json()["detail"]
        and "PATCH /tokens/bob" in r.json()["detail"]
    )
    fixed = client.patch(
        "/tokens/bob",
        headers=admin,
        json={"person": {"name": "Bob Example", "function": "Deputy Head"}},
    )
    assert fixed.status_code == 200 and fixed.json()["person"]["function"] == "Deputy Head"
    assert client.patch("/tokens/nobody", headers=admin, json={"person": person}).status_code == 404
    # bob is admin
    assert client.patch("/tokens/bob", headers=bob, json={"person": person}).status_code == 200
    r = client.post(
        f"/records/{record.id}/approve", headers=bob, json={"meaning": "approval", "note": "ok"}
    )
    assert r.status_code == 200, r.text
    assert r.json()["approval"]["signer"] == person and r.json()["approval"]["actor"] == "bob"
    # the audit trail names the person at every step: the token made, its person changed, the record
    # signed
    with store.db.session() as s:
        events = {
            (e.action, e.entity_id): e.details
            for e in s.scalars(sa.select(AuditEvent).order_by(AuditEvent.id))
        }
    assert events[("token.create", "alice")]["person"] == person
    assert events[("token.person", "bob")]["person"] == person  # the last change
    assert events[("token.person", "bob")]["previous_person"] == {
        "name": "Bob Example",
        "function": "Deputy Head",
    }
    assert events[("record.approve", str(record.id))]["signer"] == person
    # a token without a person is refused too, naming what is missing
    record2 = store.records.add_record(
        meas, "stage", "kinematic", stage_record("kinematic")["model"], operator="x", job_id=job.id
    )
    r = client.post(f"/records/{record2.id}/reject", headers=admin, json={"reason": "no"})
    assert r.status_code == 403 and "names no person" in r.json()["detail"]


def test_the_last_admin_token_cannot_be_revoked(daemon) -> None:
    """Revoking the only active admin token would lock everyone out of administration: 409, and
    the token still works; with a second admin token the first may go, and then the second is the
    last."""
    client, admin = daemon
    names = [t["name"] for t in client.get("/tokens", headers=admin).json()["tokens"]]
    assert names == ["admin"], names  # the first start's token, alone
    refused = client.delete("/tokens/admin", headers=admin)
    assert refused.status_code == 409, refused.text
    assert "last admin token" in refused.json()["detail"], refused.text
    assert client.get("/tokens", headers=admin).status_code == 200  # still an admin
    made = client.post("/tokens", headers=admin, json={"name": "deputy", "scopes": ["admin"]})
    assert made.status_code == 201, made.text
    deputy = {"Authorization": f"Bearer {made.json()['token']}"}
    # a read-only token does not count as an admin
    assert (
        client.post("/tokens", headers=admin, json={"name": "reader", "scopes": ["read"]})
    ).status_code == 201
    assert client.delete("/tokens/admin", headers=deputy).status_code == 200
    assert client.get("/tokens", headers=admin).status_code == 401
    last = client.delete("/tokens/deputy", headers=deputy)
    assert last.status_code == 409 and "last admin token" in last.json()["detail"], last.text
    assert client.get("/tokens", headers=deputy).status_code == 200
