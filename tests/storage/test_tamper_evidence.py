"""Every stored fact a result depends on is tamper-evident: an edit made in the database behind the
daemon's back (its guards dropped where it takes that) is named by `db verify`, table and row.

The lab's data: a read token and a revoked one, a reference standard, a webhook endpoint, a job's
raw samples and settled points with the record fitted on them and its approval. Each edit is made
alone on a fresh copy; `db verify` passes before it and names exactly that edit after it.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass

import pytest
import sqlalchemy as sa

from service.storage import Store, verify
from service.storage.engine import make_engine
from service.storage.migrate import downgrade, upgrade
from service.storage.samples import Sample, write_samples
from tests.helpers.storage import MODEL, STANDARDS

SHA = "a" * 64


@dataclass
class Lab:
    store: Store
    reader_id: int
    revoked_id: int
    standard_id: int
    webhook_id: int
    record_id: int
    job_id: int
    device_id: int


def _lab(store: Store) -> Lab:
    device = store.devices.add_device("NS-25/E2", "SN-TAMPER", "dut", actor="alice")
    store.tokens.create_token("admin", "admin", actor="daemon first start")
    reader, _ = store.tokens.create_token("lims", "read", actor="admin")
    gone, _ = store.tokens.create_token("old-lims", "read,operate", actor="admin")
    store.tokens.revoke_token("old-lims", actor="admin")
    standard = store.standards.add_standard(
        {
            "name": "autocollimator",
            "serial": "AC-77",
            "certificate_number": "DAkkS-2025-0412",
            "certificate_sha256": SHA,
            "calibrated_on": "2025-01-10",
            "due_on": "2027-01-10",
            "expanded_uncertainty_deg": 0.0005,
            "coverage_factor": 2.0,
        },
        actor="admin",
    )
    hook, _ = store.webhooks.add_webhook(
        "https://lims.example.org/hook", ["record.created"], actor="admin"
    )
    job = store.jobs.create_job(device.id, "scale", "linear", actor="alice")
    store.jobs.start_job(job.id, actor="alice")
    samples = [
        Sample(
            device.id,
            1_000.0 + p * 10 + i * 0.1,
            0.1 * p + 1e-4 * i,
            -0.05 * p,
            None,
            21.5,
            job.id,
            p,
            "calibration",
        )
        for p in range(4)
        for i in range(12)
    ]
    write_samples(store.engine, samples)
    store.points.settle_from_samples(job.id, device.id, actor="alice")
    record = store.records.add_record(
        device.id,
        "scale",
        "linear",
        MODEL,
        operator="alice",
        reference_standards=STANDARDS,
        job_id=job.id,
    )
    store.jobs.succeed_job(job.id, actor="alice")
    store.approvals.decide(
        record.id, actor="admin", decision="approve", meaning="approval", note="checked"
    )
    return Lab(store, reader.id, gone.id, standard.id, hook.id, record.id, job.id, device.id)


def _unguarded(conn: sa.Connection, table: str) -> None:
    """Take away an append-only table's guards, as someone with the database's owner rights
    could."""
    if conn.dialect.name == "sqlite":
        names = [
            n
            for (n,) in conn.exec_driver_sql(
                f"SELECT name FROM sqlite_master WHERE type = 'trigger' AND tbl_name = '{table}'"
            )
        ]
        for name in names:
            conn.exec_driver_sql(f"DROP TRIGGER {name}")
    else:
        conn.exec_driver_sql(f"ALTER TABLE {table} DISABLE TRIGGER USER")


def _rehash_token(conn: sa.Connection, lab: Lab) -> None:
    """Raise a token's scopes and hash the row again by the published rule: only the audit chain can
    tell."""
    from service.storage.models import ApiToken
    from service.storage.rowhash import row_sha256

    conn.execute(
        sa.text("UPDATE api_tokens SET scopes = :s WHERE id = :id"),
        {"s": json.dumps(["admin"]), "id": lab.reader_id},
    )
    with sa.orm.Session(bind=conn) as s:
        row = s.get(ApiToken, lab.reader_id)
        assert row is not None
        sha = row_sha256(row)
    conn.execute(
        sa.text("UPDATE api_tokens SET row_sha256 = :h WHERE id = :id"),
        {"h": sha, "id": lab.reader_id},
    )


def _edit_sample(conn: sa.Connection, lab: Lab) -> None:
    _unguarded(conn, "samples")
    conn.execute(
        sa.text(
            "UPDATE samples SET ch_x = ch_x + 0.001 WHERE id = (SELECT min(id) FROM samples WHERE "
            "point = 2)"
        )
    )


def _edit_point(conn: sa.Connection, lab: Lab) -> None:
    _unguarded(conn, "settled_points")
    conn.execute(sa.text("UPDATE settled_points SET ch_x_mean = ch_x_mean + 0.001 WHERE point = 1"))


def _edit_record(conn: sa.Connection, lab: Lab) -> None:
    _unguarded(conn, "calibration_records")
    conn.execute(
        sa.text("UPDATE calibration_records SET validation = :v WHERE id = :id"),
        {"v": json.dumps({"rms_deg": 0.0}), "id": lab.record_id},
    )


def _edit_audit(conn: sa.Connection, lab: Lab) -> None:
    _unguarded(conn, "audit_events")
    conn.execute(
        sa.text(
            "UPDATE audit_events SET actor = 'mallory' WHERE action = 'token.create' AND entity_id "
            "= 'lims'"
        )
    )


def _delete_approval(conn: sa.Connection, lab: Lab) -> None:
    _unguarded(conn, "record_approvals")
    conn.execute(sa.text("DELETE FROM record_approvals"))


# (what is edited, the edit, the (table, kind) verify must report, the row it names: an attribute of
# Lab or None)
EDITS: list[tuple[str, Callable[[sa.Connection, Lab], None], tuple[str, str], str | None]] = [
    (
        "a token's scopes raised",
        lambda c, lab: c.execute(
            sa.text("UPDATE api_tokens SET scopes = :s WHERE id = :id"),
            {"s": json.dumps(["read", "admin"]), "id": lab.reader_id},
        ),
        ("api_tokens", "tampered"),
        "reader_id",
    ),
    (
        "a revoked token made valid again",
        lambda c, lab: c.execute(
            sa.text("UPDATE api_tokens SET revoked_at = NULL WHERE id = :id"),
            {"id": lab.revoked_id},
        ),
        ("api_tokens", "tampered"),
        "revoked_id",
    ),
    (
        "a token's person changed (who signs what it approves)",
        lambda c, lab: c.execute(
            sa.text(
                "UPDATE api_tokens SET person_name = 'Mallory Example', person_function = "
                "'Head of Laboratory' WHERE id = :id"
            ),
            {"id": lab.reader_id},
        ),
        ("api_tokens", "tampered"),
        "reader_id",
    ),
    (
        "a token's scopes raised and its row hashed again",
        _rehash_token,
        ("api_tokens", "tampered"),
        "reader_id",
    ),
    (
        "a reference standard's uncertainty",
        lambda c, lab: c.execute(
            sa.text(
                "UPDATE reference_standards SET expanded_uncertainty_deg = 0.00005 WHERE id = :id"
            ),
            {"id": lab.standard_id},
        ),
        ("reference_standards", "tampered"),
        "standard_id",
    ),
    (
        "a reference standard's due date",
        lambda c, lab: c.execute(
            sa.text("UPDATE reference_standards SET due_on = :d WHERE id = :id"),
            {"d": dt.date(2030, 1, 1), "id": lab.standard_id},
        ),
        ("reference_standards", "tampered"),
        "standard_id",
    ),
    (
        "a webhook endpoint's URL",
        lambda c, lab: c.execute(
            sa.text(
                "UPDATE webhook_endpoints SET url = 'https://mallory.example/steal' WHERE id = :id"
            ),
            {"id": lab.webhook_id},
        ),
        ("webhook_endpoints", "tampered"),
        "webhook_id",
    ),
    ("a raw sample (its guard dropped)", _edit_sample, ("samples", "raw_data_changed"), None),
    (
        "a settled point (its guard dropped)",
        _edit_point,
        ("calibration_records", "raw_data_changed"),
        "record_id",
    ),
    (
        "a record's validation (its guard dropped)",
        _edit_record,
        ("calibration_records", "tampered"),
        "record_id",
    ),
    ("an audit event's actor (its guard dropped)", _edit_audit, ("audit_events", "tampered"), None),
    (
        "the newest approval deleted (its guard dropped)",
        _delete_approval,
        ("record_approvals", "missing"),
        None,
    ),
]


@pytest.mark.parametrize(("what", "edit", "found", "row"), EDITS, ids=[e[0] for e in EDITS])
def test_each_edit_is_named_by_db_verify(
    store: Store,
    what: str,
    edit: Callable[[sa.Connection, Lab], None],
    found: tuple[str, str],
    row: str | None,
) -> None:
    lab = _lab(store)
    before = verify(store.engine)
    assert before.ok, before.lines()
    assert before.rows_checked == 5 and before.sample_points_checked == 4
    with store.engine.begin() as conn:
        edit(conn, lab)
    report = verify(store.engine)
    named = {(p.table, p.kind) for p in report.problems}
    assert found in named, (what, report.lines())
    if row is not None:
        assert getattr(lab, row) in {
            p.row_id for p in report.problems if (p.table, p.kind) == found
        }, report.lines()
    # the edit is named where it was made, not blamed on a row it did not touch
    others = {p.table for p in report.problems} - {found[0], "calibration_records", "audit_events"}
    assert not others, report.lines()


def test_the_raw_sample_edit_names_its_job_device_and_point(store: Store) -> None:
    lab = _lab(store)
    with store.engine.begin() as conn:
        _edit_sample(conn, lab)
    lines = [str(p) for p in verify(store.engine).problems]
    assert lines == [
        (
            f"RAW_DATA_CHANGED: samples: the raw samples of device {lab.device_id} at point 2 of "
            f"job {lab.job_id} (12 stored now) no longer hash to what settled point "
            f"id={_point_id(store, lab, 2)} recorded: a sample was changed, added or removed"
        )
    ], lines


def _point_id(store: Store, lab: Lab, point: int) -> int:
    return next(
        p.id for p in store.points.settled_points(lab.job_id, lab.device_id) if p.point == point
    )


def test_a_row_changed_by_the_daemon_stays_verified(store: Store) -> None:
    """Every change the daemon makes is audited with the row's new hash: a revocation, a due-soon
    notice."""
    lab = _lab(store)
    store.tokens.revoke_token("lims", actor="admin")
    store.standards.notify_standards_due(today=dt.date(2026, 12, 20), within_days=30)
    report = verify(store.engine)
    assert report.ok, report.lines()
    # a change that no audit event anchors
    with pytest.raises(RuntimeError, match="without an audit event"):
        with store.db.transaction() as s:
            from service.storage.models import ReferenceStandard

            row = s.get(ReferenceStandard, lab.standard_id)
            assert row is not None
            row.uncertainty = "changed without a word"
    assert verify(store.engine).ok  # refused: nothing was written


def test_rows_made_before_the_hashes_are_hashed_and_anchored_by_the_migration(db_url: str) -> None:
    """A database at 0006 with a token, a standard and an endpoint: upgraded, `db verify` passes,
    and an edit of one of those rows afterwards is named."""
    engine = make_engine(db_url)
    try:
        upgrade(engine)
        downgrade(engine, "0006_certs")
        with engine.begin() as conn:  # rows as 0006 wrote them: no row_sha256 column yet
            now = dt.datetime(2026, 11, 30, 12, 0, 0, 123456, tzinfo=dt.UTC)
            at = now.replace(tzinfo=None) if engine.dialect.name == "sqlite" else now
            conn.execute(
                sa.text(
                    "INSERT INTO api_tokens (name, token_sha256, scopes, created_at, created_by)"
                    " VALUES ('lims', :h, :s, :at, 'admin')"
                ),
                {"h": hashlib.sha256(b"tl_x").hexdigest(), "s": json.dumps(["read"]), "at": at},
            )
            conn.execute(
                sa.text(
                    "INSERT INTO reference_standards (name, serial, certificate_number, "
                    "certificate_sha256, calibrated_on, due_on, uncertainty, "
                    "expanded_uncertainty_deg, coverage_factor, created_at, created_by) VALUES "
                    "('autocollimator', 'AC-77', 'C-1', :sha, :c, :d, '', 0.0005, 2.0, :at, "
                    "'admin')"
                ),
                {"sha": SHA, "c": dt.date(2025, 1, 10), "d": dt.date(2027, 1, 10), "at": at},
            )
        upgrade(engine)
        report = verify(engine)
        assert report.ok and report.rows_checked == 2, report.lines()
        with engine.begin() as conn:
            conn.execute(sa.text("UPDATE reference_standards SET coverage_factor = 1.0"))
        assert [(p.table, p.kind) for p in verify(engine).problems] == [
            ("reference_standards", "tampered")
        ]
    finally:
        engine.dispose()
