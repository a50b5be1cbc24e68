"""The database itself refuses UPDATE and DELETE on append-only tables (raw SQL, no ORM)."""

from __future__ import annotations

import pytest
import sqlalchemy as sa

from service.storage import AppendOnlyViolation, Sample, Store
from service.storage.samples import write_samples
from tests.helpers.storage import MODEL, STANDARDS, count

REFUSED = (sa.exc.IntegrityError, sa.exc.OperationalError, sa.exc.InternalError)


@pytest.fixture
def populated(store: Store, device):  # type: ignore[no-untyped-def]
    job = store.jobs.create_job(device.id, "scale", "linear", actor="alice")
    store.jobs.start_job(job.id, actor="alice")
    store.points.add_settled_points(
        job.id,
        device.id,
        [
            {
                "point": 0,
                "n_samples": 10,
                "t_start_s": 1.0,
                "t_end_s": 2.0,
                "ch_x_mean": 0.1,
                "ch_y_mean": 0.2,
            }
        ],
        actor="alice",
    )
    rec = store.records.add_record(
        device.id,
        "scale",
        "linear",
        MODEL,
        operator="alice",
        reference_standards=STANDARDS,
        job_id=job.id,
        activate=True,
    )
    write_samples(
        store.engine,
        [
            Sample(device.id, 100.0, 0.1, 0.2, job_id=job.id, point=0, source="calibration"),
            Sample(device.id, 101.0, 0.1, 0.2),
        ],
    )
    return rec


@pytest.mark.parametrize(
    "table", ["calibration_records", "audit_events", "active_calibration_history", "settled_points"]
)
@pytest.mark.parametrize("verb", ["UPDATE", "DELETE"])
def test_triggers_refuse_update_and_delete(store: Store, populated, table: str, verb: str) -> None:  # type: ignore[no-untyped-def]
    before = count(store.engine, table)
    sql = f"UPDATE {table} SET id = id" if verb == "UPDATE" else f"DELETE FROM {table}"
    with pytest.raises(REFUSED, match="append-only"):
        with store.engine.begin() as conn:
            conn.exec_driver_sql(sql)
    assert count(store.engine, table) == before


def test_raw_samples_are_never_updated_and_calibration_samples_never_deleted(
    store: Store, populated
) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(REFUSED, match="raw data"):
        with store.engine.begin() as conn:
            conn.exec_driver_sql("UPDATE samples SET ch_x = 0")
    with pytest.raises(REFUSED, match="kept"):
        with store.engine.begin() as conn:
            conn.exec_driver_sql("DELETE FROM samples")
    assert count(store.engine, "samples") == 2
    with store.engine.begin() as conn:  # monitoring samples may go (retention)
        conn.exec_driver_sql("DELETE FROM samples WHERE source = 'monitoring'")
    assert count(store.engine, "samples") == 1


def test_orm_update_of_a_record_is_refused_with_a_clear_error(store: Store, populated) -> None:  # type: ignore[no-untyped-def]
    from service.storage.models import CalibrationRecord

    with store.db.session() as s:
        rec = s.get(CalibrationRecord, populated.id)
        rec.model = {**rec.model, "parameters": {"gain_x": 2.0}}
        with pytest.raises(AppendOnlyViolation, match="append-only.*cannot update"):
            s.commit()
    with store.db.session() as s:
        s.delete(s.get(CalibrationRecord, populated.id))
        with pytest.raises(AppendOnlyViolation, match="cannot delete"):
            s.commit()
    assert store.records.get_record(populated.id).model == MODEL


def test_database_refusal_is_translated(store: Store, populated) -> None:  # type: ignore[no-untyped-def]
    """An update that reaches the database through the store's transaction surfaces as
    AppendOnlyViolation."""
    with pytest.raises(AppendOnlyViolation, match="append-only"):
        with store.db.transaction() as s:
            s.execute(sa.text("UPDATE calibration_records SET operator = 'mallory'"))
    assert store.records.get_record(populated.id).operator == "alice"
