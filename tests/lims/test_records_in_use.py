"""Records in use, in storage: a rejected or altered record is never activated, rejecting the active
record withdraws it, and `db verify` covers every input of a record (all sensors' settled points,
the newest decision)."""

from __future__ import annotations

import pytest
import sqlalchemy as sa

from service.storage.errors import RecordNotUsable
from service.storage.verify import verify


def _drop_guards(engine: sa.Engine, *tables: str) -> None:
    """What someone with write access to the database file could do: remove the append-only
    guards."""
    with engine.begin() as conn:
        for table in tables:
            if engine.dialect.name == "sqlite":
                for (name,) in conn.exec_driver_sql(
                    "SELECT name FROM sqlite_master WHERE type = 'trigger' AND tbl_name = "
                    f"'{table}'"
                ).all():
                    conn.exec_driver_sql(f"DROP TRIGGER {name}")
            else:
                conn.exec_driver_sql(f"ALTER TABLE {table} DISABLE TRIGGER USER")


def _points(n: int, offset: float) -> list[dict]:
    return [
        {
            "point": p,
            "n_samples": 10,
            "t_start_s": float(p),
            "t_end_s": p + 1.0,
            "ch_x_mean": offset + 0.1 * p,
            "ch_y_mean": offset - 0.05 * p,
        }
        for p in range(n)
    ]


def stage_record(lims):  # type: ignore[no-untyped-def]
    """A stage record fitted on a job's points of the measurement sensor and of the reference
    sensor."""
    meas = lims.devices.add_device("NS-25", "SN-4711", "dut", actor="alice")
    ref = lims.devices.add_device("REF-1", "R-1", "reference", actor="alice")
    job = lims.jobs.create_job(meas.id, "stage", "kinematic", actor="alice")
    lims.jobs.start_job(job.id, actor="alice")
    lims.points.add_settled_points(job.id, ref.id, _points(5, 0.0), actor="alice")
    lims.points.add_settled_points(job.id, meas.id, _points(5, 0.3), actor="alice")
    record = lims.records.add_record(
        meas.id, "stage", "kinematic", {"parameters": {}}, operator="alice", job_id=job.id
    )
    lims.jobs.succeed_job(job.id, actor="alice")
    return record, meas, ref


def test_rejecting_the_active_record_withdraws_it_and_it_cannot_be_activated_again(lims) -> None:  # type: ignore[no-untyped-def]
    record, meas, _ = stage_record(lims)
    # a draft may be used
    lims.records.activate(record.id, actor="alice", reason="first use", replaces=None)
    assert lims.records.unusable_reason(record.id) is None
    lims.approvals.decide(
        record.id,
        decision="reject",
        meaning="rejection",
        note="reference sensor out of date",
        actor="bob",
    )
    assert lims.records.active_record(meas.id, "stage") is None
    why = lims.records.inactive_reason(meas.id, "stage")
    assert (
        why is not None
        and f"record {record.id}" in why
        and "rejected" in why
        and "out of date" in why
    )
    (last, *_) = lims.audit.events(entity="active_calibration")
    assert last.action == "pointer.clear" and last.details["previous_record_id"] == record.id
    assert "rejected by bob" in (lims.records.unusable_reason(record.id) or "")
    with pytest.raises(RecordNotUsable, match="rejected"):
        lims.records.activate(record.id, actor="alice", reason="again", replaces=None)
    assert lims.records.active_record(meas.id, "stage") is None
    assert verify(lims.engine).ok


def test_rejecting_a_record_that_is_not_active_leaves_the_active_one(lims) -> None:  # type: ignore[no-untyped-def]
    first, meas, _ = stage_record(lims)
    lims.records.activate(first.id, actor="alice", reason="first use", replaces=None)
    second = lims.records.add_record(
        meas.id, "stage", "kinematic", {"parameters": {}}, operator="alice"
    )
    lims.approvals.decide(
        second.id, decision="reject", meaning="rejection", note="bad fit", actor="bob"
    )
    active = lims.records.active_record(meas.id, "stage")
    assert active is not None and active.id == first.id


def test_an_altered_record_cannot_be_activated(lims) -> None:  # type: ignore[no-untyped-def]
    record, meas, _ = stage_record(lims)
    _drop_guards(lims.engine, "calibration_records")
    with lims.engine.begin() as conn:
        conn.execute(
            sa.text("UPDATE calibration_records SET model = :m WHERE id = :i"),
            {"m": '{"parameters":{"offset":1.0}}', "i": record.id},
        )
    assert "does not match its SHA-256" in (lims.records.unusable_reason(record.id) or "")
    with pytest.raises(RecordNotUsable, match="SHA-256"):
        lims.records.activate(record.id, actor="alice", reason="use it", replaces=None)
    assert lims.records.active_record(meas.id, "stage") is None


@pytest.mark.parametrize("role", ["reference", "measurement"])
def test_db_verify_sees_an_edit_of_any_sensors_settled_point(lims, role) -> None:  # type: ignore[no-untyped-def]
    record, meas, ref = stage_record(lims)
    assert verify(lims.engine).ok
    device = ref if role == "reference" else meas
    _drop_guards(lims.engine, "settled_points")
    with lims.engine.begin() as conn:
        conn.execute(
            sa.text(
                "UPDATE settled_points SET ch_x_mean = ch_x_mean + 0.001 "
                "WHERE job_id = :j AND device_id = :d AND point = 3"
            ),
            {"j": record.job_id, "d": device.id},
        )
    problems = verify(lims.engine).problems
    assert [(p.table, p.row_id, p.kind) for p in problems] == [
        ("calibration_records", record.id, "raw_data_changed")
    ]
    assert f"device {device.id}" in problems[0].detail


def test_db_verify_sees_the_deletion_of_the_newest_decision(lims) -> None:  # type: ignore[no-untyped-def]
    record, _, _ = stage_record(lims)
    lims.approvals.decide(
        record.id, decision="approve", meaning="review", note="looked at", actor="carol"
    )
    rejection = lims.approvals.decide(
        record.id, decision="reject", meaning="rejection", note="drifting", actor="bob"
    )
    assert lims.approvals.record_status(record.id) == "rejected"
    report = verify(lims.engine)
    assert report.ok and report.approvals_checked == 2
    _drop_guards(lims.engine, "record_approvals")
    with lims.engine.begin() as conn:
        conn.execute(sa.text("DELETE FROM record_approvals WHERE id = :i"), {"i": rejection.id})
    assert lims.approvals.record_status(record.id) == "draft"  # what the deletion would make of it
    problems = verify(lims.engine).problems
    assert [(p.table, p.row_id, p.kind) for p in problems] == [
        ("record_approvals", rejection.id, "missing")
    ]
    assert "record.reject" in problems[0].detail
