"""Calibration records: versions, hash chain, active pointer, refused writes, tamper detection."""

from __future__ import annotations

import pytest
import sqlalchemy as sa

from service import cli
from service.config import get_settings
from service.errors import InputError
from service.storage import (
    ConflictError,
    IllegalTransition,
    RefusedWrite,
    Store,
    UnknownEntity,
    verify,
)
from service.storage.canonical import sha256_hex
from service.storage.models import GENESIS_SHA256
from service.storage.store import record_content
from tests.helpers.storage import MODEL, STANDARDS, count

WRITE_TABLES = (
    "calibration_records",
    "audit_events",
    "active_calibrations",
    "active_calibration_history",
)


def _counts(store: Store) -> dict[str, int]:
    return {t: count(store.engine, t) for t in WRITE_TABLES}


def _record(store: Store, device_id: int, **kw):  # type: ignore[no-untyped-def]
    kw.setdefault("operator", "alice")
    kw.setdefault("reference_standards", STANDARDS)
    return store.records.add_record(device_id, "scale", "linear", MODEL, temp_c=21.4, **kw)


def _drop_guards(engine: sa.Engine) -> None:
    """What an attacker with file access could do: remove the triggers, then edit."""
    with engine.begin() as conn:
        if engine.dialect.name == "sqlite":
            for (name,) in conn.exec_driver_sql(
                "SELECT name FROM sqlite_master WHERE type = 'trigger'"
            ).all():
                conn.exec_driver_sql(f"DROP TRIGGER {name}")
        else:
            for table in ("calibration_records", "audit_events", "settled_points"):
                conn.exec_driver_sql(f"ALTER TABLE {table} DISABLE TRIGGER USER")


def test_versions_form_a_hash_chain(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    r1 = _record(store, device.id, activate=True)
    r2 = _record(store, device.id)
    r3 = _record(store, device.id)
    assert [r.version for r in (r1, r2, r3)] == [1, 2, 3]
    assert r1.prev_sha256 == GENESIS_SHA256
    assert r2.prev_sha256 == r1.content_sha256 and r3.prev_sha256 == r2.content_sha256
    assert r2.supersedes_id == r1.id and r3.supersedes_id == r1.id  # the active one, until switched
    stored = store.records.get_record(r2.id)
    assert (
        stored.model == MODEL and stored.reference_standards == STANDARDS and stored.temp_c == 21.4
    )
    assert stored.content_sha256 == sha256_hex(record_content(stored))
    assert stored.created_at.tzinfo is not None
    report = verify(store.engine)
    assert report.ok, report.lines()
    assert report.records_checked == 3


def test_active_pointer_switch_is_deliberate_and_audited(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    r1 = _record(store, device.id)
    r2 = _record(store, device.id)
    assert store.records.active_record(device.id, "scale") is None
    store.records.activate(r1.id, actor="bob", reason="validated against AC-77")
    assert store.records.active_record(device.id, "scale").id == r1.id
    store.records.activate(r2.id, actor="bob", reason="recalibrated", replaces=r1.id)
    assert store.records.active_record(device.id, "scale").id == r2.id
    history = store.records.pointer_history(device.id, "scale")
    assert [(h.previous_record_id, h.record_id) for h in history] == [(None, r1.id), (r1.id, r2.id)]
    store.records.deactivate(
        device.id, "scale", actor="bob", reason="drop test failed", replaces=r2.id
    )
    assert store.records.active_record(device.id, "scale") is None
    actions = [e.action for e in store.audit.events(entity="active_calibration")]
    assert actions == ["pointer.clear", "pointer.set", "pointer.set"]
    assert verify(store.engine).ok


def test_second_active_pointer_is_refused(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    r1 = _record(store, device.id, activate=True)
    r2 = _record(store, device.id)
    before = _counts(store)
    with pytest.raises(ConflictError, match="second active pointer is refused.*replaces="):
        store.records.activate(r2.id, actor="bob", reason="oops")
    with pytest.raises(ConflictError):
        store.records.activate(r2.id, actor="bob", reason="stale view", replaces=r2.id)
    assert _counts(store) == before
    assert store.records.active_record(device.id, "scale").id == r1.id
    # The database refuses it too, whoever writes: (device, kind) is the pointer's primary key.
    with pytest.raises(sa.exc.IntegrityError):
        with store.engine.begin() as conn:
            conn.execute(
                sa.text(
                    "INSERT INTO active_calibrations (device_id, kind, record_id, set_at, "
                    "set_by, reason) VALUES (:d, 'scale', :r, CURRENT_TIMESTAMP, 'mallory', 'x')"
                ),
                {"d": device.id, "r": r2.id},
            )
    assert _counts(store) == before


def test_pointer_cannot_name_a_record_of_another_device(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    other = store.devices.add_device("NS-25/E2", "SN1002", "dut", actor="alice")
    rec = _record(store, other.id)
    with pytest.raises(sa.exc.IntegrityError):
        with store.engine.begin() as conn:
            conn.execute(
                sa.text(
                    "INSERT INTO active_calibrations (device_id, kind, record_id, set_at, "
                    "set_by, reason) VALUES (:d, 'scale', :r, CURRENT_TIMESTAMP, 'mallory', 'x')"
                ),
                {"d": device.id, "r": rec.id},
            )


def test_record_for_unknown_device_is_refused_and_nothing_is_left(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    before = _counts(store)
    with pytest.raises(UnknownEntity, match="device 999 does not exist"):
        _record(store, 999)
    assert _counts(store) == before
    with pytest.raises(sa.exc.IntegrityError):  # and at the database level
        with store.engine.begin() as conn:
            conn.execute(
                sa.text(
                    "INSERT INTO calibration_records (device_id, kind, version, content_format, "
                    "method, model, validation, reference_standards, operator, created_at, "
                    "raw_data, prev_sha256, content_sha256) VALUES (999, 'scale', 1, 1, "
                    "'linear', '{}', '{}', '[]', 'm', CURRENT_TIMESTAMP, '{}', :z, :z)"
                ),
                {"z": "0" * 64},
            )
    assert _counts(store) == before


@pytest.mark.parametrize(
    ("change", "error", "match"),
    [
        ({"model": {"parameters": {"g": float("nan")}}}, InputError, "not a finite number"),
        ({"model": {**MODEL, "kind": "stage"}}, InputError, "model document says kind"),
        ({"reference_standards": [{"name": "AC"}]}, InputError, "certificate_id"),
        ({"operator": ""}, InputError, "operator"),
        ({"supersedes_id": 12345}, UnknownEntity, "record 12345"),
        ({"job_id": 12345}, UnknownEntity, "job 12345"),
    ],
)
def test_invalid_records_are_refused_whole(store: Store, device, change, error, match) -> None:  # type: ignore[no-untyped-def]
    _record(store, device.id, activate=True)
    before = _counts(store)
    kw = {"operator": "alice", "reference_standards": STANDARDS, "activate": True} | change
    model = kw.pop("model", MODEL)
    with pytest.raises(error, match=match):
        store.records.add_record(device.id, "scale", "linear", model, **kw)
    assert _counts(store) == before


def test_record_from_a_job_of_another_device_or_an_unfinished_job(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    other = store.devices.add_device("NS-25/E2", "SN1002", "dut", actor="alice")
    job = store.jobs.create_job(other.id, "scale", "linear", actor="alice")
    with pytest.raises(InputError, match="calibrates device"):
        _record(store, device.id, job_id=job.id)
    with pytest.raises(IllegalTransition, match="queued"):
        _record(store, other.id, job_id=job.id)
    assert count(store.engine, "calibration_records") == 0


def test_tampered_record_is_reported(store: Store, device, db_url, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    r1 = _record(store, device.id, activate=True)
    _record(store, device.id)
    _drop_guards(store.engine)
    with store.engine.begin() as conn:
        conn.execute(
            sa.text("UPDATE calibration_records SET temp_c = 25.0 WHERE id = :i"), {"i": r1.id}
        )
    report = verify(store.engine)
    assert not report.ok
    assert [(p.row_id, p.kind) for p in report.problems] == [(r1.id, "tampered")]
    # the tampered version cannot be re-activated either
    store.records.deactivate(
        device.id, "scale", actor="bob", reason="hash mismatch", replaces=r1.id
    )
    with pytest.raises(RefusedWrite, match="tampered"):
        store.records.activate(r1.id, actor="bob", reason="x")
    # and `tiltlab db verify` says so and exits 1
    monkeypatch.delenv("TILTLAB_CONFIG", raising=False)
    monkeypatch.setenv("TILTLAB_DATABASE_URL", db_url)
    get_settings.cache_clear()
    try:
        assert cli.main(["db", "verify"]) == 1
    finally:
        get_settings.cache_clear()
    out = capsys.readouterr().out
    assert f"TAMPERED: calibration_records id={r1.id}" in out and "FAILED" in out


def test_rehashed_edit_breaks_the_chain(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    """Editing a row and recomputing its own hash still leaves its successor pointing at the old
    hash."""
    r1 = _record(store, device.id)
    r2 = _record(store, device.id)
    _drop_guards(store.engine)
    forged = store.records.get_record(r1.id)
    forged.temp_c = 25.0
    with store.engine.begin() as conn:
        conn.execute(
            sa.text(
                "UPDATE calibration_records SET temp_c = 25.0, content_sha256 = :h WHERE id = :i"
            ),
            {"h": sha256_hex(record_content(forged)), "i": r1.id},
        )
    kinds = {(p.row_id, p.kind) for p in verify(store.engine).problems}
    assert (r2.id, "broken_chain") in kinds
    assert (r1.id, "tampered") in kinds  # its creation event still holds the original hash


def test_removed_records_are_detected(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    r1, r2, r3 = (_record(store, device.id) for _ in range(3))
    _drop_guards(store.engine)
    with store.engine.begin() as conn:
        conn.execute(
            sa.text("DELETE FROM calibration_records WHERE id IN (:a, :b)"),
            {"a": r2.id, "b": r3.id},
        )
        # r3 (the newest) leaves no gap in the chain; its audit event gives it away.
    problems = {(p.row_id, p.kind) for p in verify(store.engine).problems}
    assert (r2.id, "missing") in problems and (r3.id, "missing") in problems
    assert (r1.id, "missing") not in problems


def test_version_gap_is_a_broken_chain(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    r1, r2, r3 = (_record(store, device.id) for _ in range(3))
    _drop_guards(store.engine)
    with store.engine.begin() as conn:
        conn.execute(
            sa.text("UPDATE calibration_records SET supersedes_id = NULL WHERE id = :b"),
            {"b": r3.id},
        )
        conn.execute(sa.text("DELETE FROM calibration_records WHERE id = :b"), {"b": r2.id})
    problems = {(p.row_id, p.kind) for p in verify(store.engine).problems}
    assert (r3.id, "broken_chain") in problems


def test_audit_log_tamper_and_removal_are_detected(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    _record(store, device.id)
    store.devices.add_device("X", "Y", "reference", actor="alice")
    events = sorted(store.audit.events(), key=lambda e: e.id)
    assert len(events) >= 3 and verify(store.engine).ok
    _drop_guards(store.engine)
    with store.engine.begin() as conn:
        conn.execute(
            sa.text("UPDATE audit_events SET actor = 'mallory' WHERE id = :i"), {"i": events[0].id}
        )
    assert [(p.row_id, p.kind) for p in verify(store.engine).problems] == [
        (events[0].id, "tampered")
    ]
    with store.engine.begin() as conn:
        conn.execute(sa.text("DELETE FROM audit_events WHERE id = :i"), {"i": events[1].id})
    assert (events[2].id, "broken_chain") in {
        (p.row_id, p.kind) for p in verify(store.engine).problems
    }


def test_every_action_is_audited_with_who_what_when(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    bench = store.devices.add_bench(
        "bench-1", actor="carol", stage_model="PI H-811", port="/dev/ttyS0"
    )
    store.devices.update_device(device.id, actor="carol", bench_id=bench.id, port="/dev/ttyUSB1")
    _record(store, device.id, activate=True)
    events = sorted(store.audit.events(), key=lambda e: e.id)
    assert [e.action for e in events] == [
        "device.create",
        "bench.create",
        "device.update",
        "record.create",
        "pointer.set",
    ]
    assert all(e.at.tzinfo is not None and e.actor for e in events)
    assert events[2].details["before"]["port"] == "/dev/ttyUSB0"
    assert events[0].prev_sha256 == GENESIS_SHA256
    assert all(b.prev_sha256 == a.sha256 for a, b in zip(events, events[1:], strict=False))


def test_duplicate_device_and_unknown_bench_are_refused(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ConflictError, match="already exists"):
        store.devices.add_device("NS-25/E2", "SN1001", "dut", actor="alice")
    with pytest.raises(UnknownEntity, match="bench 77"):
        store.devices.add_device("NS-25/E2", "SN1009", "dut", actor="alice", bench_id=77)
    with pytest.raises(InputError, match="cannot change"):
        store.devices.update_device(device.id, actor="alice", serial="SN9")
    assert count(store.engine, "devices") == 1


def test_optional_text_fields_are_checked_the_same_on_every_backend(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    """SQLite does not enforce column lengths or types; PostgreSQL does: the store checks first, for
    both."""
    tables = ("benches", "devices", "audit_events")
    before = [count(store.engine, t) for t in tables]
    with pytest.raises(InputError, match="port is longer than 200"):
        store.devices.add_bench("bench-1", actor="carol", port="p" * 201)
    with pytest.raises(InputError, match="stage_model is longer than 100"):
        store.devices.add_bench("bench-1", actor="carol", stage_model="m" * 101)
    with pytest.raises(InputError, match="stage_serial must be"):
        store.devices.add_bench("bench-1", actor="carol", stage_serial=5)
    with pytest.raises(InputError, match="port is longer than 200"):
        store.devices.add_device("NS-25/E2", "SN1009", "dut", actor="carol", port="q" * 201)
    with pytest.raises(InputError, match="port must be"):
        store.devices.update_device(device.id, actor="carol", port=7)
    assert [count(store.engine, t) for t in tables] == before
    store.devices.update_device(device.id, actor="carol", port=None)  # None still clears it
    assert store.devices.get_device(device.id).port is None
