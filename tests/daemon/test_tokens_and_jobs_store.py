"""Tokens kept as hashes with implied scopes, the token commands, and the daemon's job
bookkeeping."""

from __future__ import annotations

import hashlib

import pytest
import sqlalchemy as sa

from service import cli
from service.config import get_settings
from service.errors import InputError
from service.storage.engine import make_engine
from service.storage.errors import ConflictError, UnknownEntity
from service.storage.migrate import upgrade
from service.storage.store import Store
from service.storage.store.jobs import IdempotencyMismatch


@pytest.fixture
def dstore(tmp_path):
    engine = make_engine(f"sqlite:///{tmp_path / 'd.db'}")
    upgrade(engine)
    yield Store(engine)
    engine.dispose()


def test_token_is_stored_only_as_its_hash_and_scopes_imply(dstore):
    row, token = dstore.tokens.create_token("lims", "operate", actor="t")
    with dstore.engine.connect() as c:
        stored = c.execute(sa.text("SELECT token_sha256 FROM api_tokens")).scalar()
        dump = "\n".join(str(r) for r in c.execute(sa.text("SELECT * FROM api_tokens")))
    assert token not in dump and stored == hashlib.sha256(token.encode()).hexdigest()
    p = dstore.tokens.authenticate(token)
    assert p.name == "lims" and p.may("read") and p.may("operate") and not p.may("admin")
    assert dstore.tokens.authenticate(token + "x") is None
    _, admin = dstore.tokens.create_token("boss", ["admin"], actor="t")
    assert dstore.tokens.authenticate(admin).scopes == {"read", "operate", "admin"}
    dstore.tokens.revoke_token("lims", actor="t")
    assert dstore.tokens.authenticate(token) is None
    with pytest.raises(UnknownEntity):
        dstore.tokens.revoke_token("lims", actor="t")
    assert [e.action for e in dstore.audit.events(entity="api_token")][:3] == [
        "token.revoke",
        "token.create",
        "token.create",
    ]


@pytest.mark.parametrize(
    "name,scopes", [("a b", "read"), ("ok", "write"), ("ok", ""), ("", "read")]
)
def test_bad_token_requests_are_refused(dstore, name, scopes):
    with pytest.raises(InputError):
        dstore.tokens.create_token(name, scopes, actor="t")
    assert dstore.tokens.all() == []


def test_duplicate_name_refused(dstore):
    dstore.tokens.create_token("x", "read", actor="t")
    with pytest.raises(ConflictError):
        dstore.tokens.create_token("x", "read", actor="t")


def test_token_commands(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("TILTLAB_DATA_DIR", str(tmp_path))
    get_settings.cache_clear()
    try:
        assert cli.main(["token", "create", "--name", "lims", "--scopes", "read,operate"]) == 0
        token = capsys.readouterr().out.strip()
        assert token.startswith("tl_")
        assert cli.main(["token", "list"]) == 0
        out = capsys.readouterr().out
        assert "lims\tread,operate" in out and token not in out
        assert cli.main(["token", "create", "--name", "x", "--scopes", "root"]) == 2
        assert "root unknown" in capsys.readouterr().err
        assert cli.main(["token", "revoke", "lims"]) == 0
        assert cli.main(["token", "revoke", "lims"]) == 2
        capsys.readouterr()
        assert cli.main(["token", "list", "--all"]) == 0
        assert "revoked" in capsys.readouterr().out
    finally:
        get_settings.cache_clear()


def test_token_commands_name_the_person(tmp_path, monkeypatch, capsys):
    """`tiltlab token create --person-name --person-function`, `token set-person`; `token list`
    shows the person."""
    monkeypatch.setenv("TILTLAB_DATA_DIR", str(tmp_path))
    get_settings.cache_clear()
    try:
        assert (
            cli.main(
                [
                    "token",
                    "create",
                    "--name",
                    "alice",
                    "--scopes",
                    "admin",
                    "--person-name",
                    "Dr. Alice Example",
                    "--person-function",
                    "Head of Laboratory",
                ]
            )
            == 0
        )
        assert "belonging to Dr. Alice Example, Head of Laboratory" in capsys.readouterr().err
        assert cli.main(["token", "create", "--name", "bench-pc", "--scopes", "operate"]) == 0
        capsys.readouterr()
        assert (
            cli.main(
                [
                    "token",
                    "set-person",
                    "bench-pc",
                    "--person-name",
                    "Max Muster",
                    "--person-function",
                    "Calibration Technician",
                ]
            )
            == 0
        )
        capsys.readouterr()
        assert cli.main(["token", "list"]) == 0
        lines = {line.split("\t")[0]: line for line in capsys.readouterr().out.splitlines()}
        assert lines["alice"].endswith("\tDr. Alice Example, Head of Laboratory")
        assert lines["bench-pc"].endswith("\tMax Muster, Calibration Technician")
        assert (
            cli.main(
                ["token", "create", "--name", "x", "--scopes", "read", "--person-function", "Head"]
            )
            == 2
        )
        assert "--person-function: give --person-name with it" in capsys.readouterr().err
        assert cli.main(["token", "set-person", "nobody", "--person-name", "N. N."]) == 2
        assert "no active token named 'nobody'" in capsys.readouterr().err
    finally:
        get_settings.cache_clear()


def test_job_idempotency_interruption_and_resume(dstore):
    bench = dstore.devices.ensure_bench("b1", actor="t")
    dev = dstore.devices.add_device("M", "1", "measurement_sensor", actor="t", bench_id=bench.id)
    body = {"bench": "b1", "procedure": "stage-grid"}
    job, created = dstore.jobs.create_calibration_job(
        bench_id=bench.id,
        device_id=dev.id,
        kind="stage",
        method="kinematic",
        parameters=body,
        actor="t",
        points_total=9,
        idempotency_key="k1",
        request=body,
    )
    assert created
    again, created = dstore.jobs.create_calibration_job(
        bench_id=bench.id,
        device_id=dev.id,
        kind="stage",
        method="kinematic",
        parameters=body,
        actor="t",
        points_total=9,
        idempotency_key="k1",
        request=body,
    )
    assert not created and again.id == job.id
    with pytest.raises(IdempotencyMismatch):
        dstore.jobs.create_calibration_job(
            bench_id=bench.id,
            device_id=dev.id,
            kind="stage",
            method="homography",
            parameters=body,
            actor="t",
            points_total=9,
            idempotency_key="k1",
            request={**body, "method": "homography"},
        )
    assert len(dstore.jobs.all()) == 1
    dstore.jobs.start_job(job.id, actor="t")
    dstore.jobs.set_job_progress(job.id, points_done=4, points_total=9, phase="measuring")
    assert dstore.jobs.mark_interrupted(actor="restart") == [job.id]
    j = dstore.jobs.get_job(job.id)
    assert (
        j.state == "failed"
        and j.interrupted
        and j.points_done == 4
        and "interrupted" in j.failure_reason
    )
    r = dstore.jobs.resume_job(job.id, actor="t")
    assert r.state == "running" and not r.interrupted
    dstore.jobs.fail_job(job.id, "sensor gone", actor="t")
    with pytest.raises(ConflictError):
        dstore.jobs.resume_job(job.id, actor="t")
    assert [j.id for j in dstore.jobs.list_jobs(state="failed", bench_id=bench.id)] == [job.id]
    assert dstore.jobs.list_jobs(before_id=job.id) == []


def test_a_job_follower_reads_only_the_points_it_has_not_had(dstore, monkeypatch):
    """The job stream's point reads start at the first point it lacks; a point half stored (one
    instrument of two) waits until both are; points had earlier are never sent again."""
    from service.streams.jobs import job_points

    bench = dstore.devices.ensure_bench("b1", actor="t")
    ref = dstore.devices.add_device("R", "1", "reference_sensor", actor="t", bench_id=bench.id)
    meas = dstore.devices.add_device("M", "1", "measurement_sensor", actor="t", bench_id=bench.id)
    params = {"device_ids": {"reference_sensor": ref.id, "measurement_sensor": meas.id}}
    job, _ = dstore.jobs.create_calibration_job(
        bench_id=bench.id,
        device_id=meas.id,
        kind="stage",
        method="kinematic",
        parameters=params,
        actor="t",
        points_total=6,
    )
    dstore.jobs.start_job(job.id, actor="t")

    def point(i):
        return {
            "point": i,
            "cmd_x_deg": float(i),
            "cmd_y_deg": 0.0,
            "n_samples": 4,
            "t_start_s": 1.0 * i,
            "t_end_s": 1.0 * i + 0.5,
            "ch_x_mean": 0.1 * i,
            "ch_y_mean": 0.0,
        }

    for i in (0, 1, 2):
        dstore.points.add_settled_points(job.id, ref.id, [point(i)], actor="t")
        dstore.points.add_settled_points(job.id, meas.id, [point(i)], actor="t")
    # point 3: one instrument so far
    dstore.points.add_settled_points(job.id, ref.id, [point(3)], actor="t")
    job = dstore.jobs.get_job(job.id)
    asked = []
    read = dstore.points.settled_points
    monkeypatch.setattr(
        dstore.points,
        "settled_points",
        lambda *a, **k: asked.append(k.get("from_point")) or read(*a, **k),
    )
    assert [p["index"] for p in job_points(dstore.points, job)] == [0, 1, 2]
    assert [p["index"] for p in job_points(dstore.points, job, {0, 1, 2})] == []
    dstore.points.add_settled_points(job.id, meas.id, [point(3)], actor="t")
    got = job_points(dstore.points, job, {0, 1, 2})
    assert [p["index"] for p in got] == [3] and got[0]["measurement_sensor"][
        "x_deg"
    ] == pytest.approx(0.3)
    assert asked == [0, 3, 3]
    # a gap (a resumed job measures a point it skipped): reads start at the gap, the rest is not
    # resent
    assert [p["index"] for p in job_points(dstore.points, job, {0, 2, 3})] == [1]
