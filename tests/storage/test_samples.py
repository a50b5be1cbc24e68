"""Raw samples: bulk path, latest-N read, SampleWriter (no loss on close, back-pressure), settled
points, retention."""

from __future__ import annotations

import datetime as dt
import threading
from types import SimpleNamespace

import pytest
import sqlalchemy as sa

from service.errors import InputError
from service.storage import (
    BackPressureTimeout,
    IllegalTransition,
    Sample,
    SampleWriteError,
    SampleWriter,
    Store,
    latest_samples,
    verify,
    write_engine,
)
from service.storage.engine import make_engine
from service.storage.samples import count_samples, job_samples, write_samples
from tests.helpers.storage import MODEL, STANDARDS, count

NOW = dt.datetime(2026, 3, 1, 12, 0, tzinfo=dt.UTC)
DAY_S = 86400.0


def test_latest_samples_newest_first(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    other = store.devices.add_device("NS-25/E2", "SN2", "dut", actor="a")
    rows = [Sample(device.id, 1000.0 + i, i * 1e-3, -i * 1e-3, None, 21.0) for i in range(2500)]
    rows += [Sample(other.id, 5000.0 + i, 0.0, 0.0) for i in range(10)]
    assert write_samples(store.engine, rows, batch_size=1000) == 2510
    with store.engine.connect() as conn:
        latest = latest_samples(conn, device.id, 1000)
    assert len(latest) == 1000
    assert latest[0] == rows[2499] and latest[-1] == rows[1500]


def test_writer_loses_nothing_on_clean_close(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    producers, per_producer = 4, 6000
    writer = SampleWriter(store.engine, capacity=3000, batch_size=700, put_timeout_s=30)

    def produce(k: int) -> None:
        for start in range(0, per_producer, 250):
            writer.put_many(
                [
                    Sample(device.id, k * 1e6 + i, float(k), float(i))
                    for i in range(start, start + 250)
                ]
            )
        writer.put(Sample(device.id, k * 1e6 + per_producer, float(k), -1.0))

    threads = [threading.Thread(target=produce, args=(k,)) for k in range(producers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    writer.close()
    expected = producers * (per_producer + 1)
    assert writer.handed_over == writer.committed == expected
    assert count(store.engine, "samples") == expected
    with store.engine.connect() as conn:
        per_k = conn.execute(
            sa.text("SELECT ch_x, count(*) FROM samples GROUP BY ch_x ORDER BY ch_x")
        ).all()
    assert [tuple(r) for r in per_k] == [(float(k), per_producer + 1) for k in range(producers)]


def test_flush_makes_everything_visible(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    with SampleWriter(store.engine, capacity=100, batch_size=10) as writer:
        writer.put_many([Sample(device.id, float(i), 0.0, 0.0) for i in range(55)])
        writer.flush(timeout=30)
        assert count(store.engine, "samples") == 55
    with pytest.raises(RuntimeError, match="closed"):
        writer.put(Sample(device.id, 1.0, 0.0, 0.0))


def _hold_write_lock(engine: sa.Engine) -> sa.Connection:
    conn = write_engine(engine).connect()
    conn.begin()  # SQLite: BEGIN IMMEDIATE takes the write lock
    if engine.dialect.name == "postgresql":
        conn.exec_driver_sql("LOCK TABLE samples IN ACCESS EXCLUSIVE MODE")
    return conn


def test_back_pressure_blocks_then_times_out(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    engine = store.engine
    holder = _hold_write_lock(engine)
    writer = SampleWriter(engine, capacity=200, batch_size=50, put_timeout_s=0.3, retry_for_s=60)
    try:
        # queue + one batch in flight
        writer.put_many([Sample(device.id, float(i), 0.0, 0.0) for i in range(250)])
        with pytest.raises(BackPressureTimeout, match="not keeping up"):
            writer.put_many([Sample(device.id, 1e6 + i, 0.0, 0.0) for i in range(50)])
        assert writer.handed_over == 250
    finally:
        holder.rollback()
        holder.close()
    writer.close()
    assert writer.committed == 250 and count(store.engine, "samples") == 250


def test_writer_isolates_a_bad_sample(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    writer = SampleWriter(store.engine, capacity=100, batch_size=20)
    good = [Sample(device.id, float(i), 0.0, 0.0) for i in range(30)]
    writer.put_many([*good[:10], Sample(999, 5.5, 0.0, 0.0), *good[10:]])
    with pytest.raises(SampleWriteError, match="1 samples were refused"):
        writer.close()
    assert writer.committed == 30 and count(store.engine, "samples") == 30


def test_bad_samples_are_refused_at_the_producer(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    with SampleWriter(store.engine, capacity=10, batch_size=5) as writer:
        with pytest.raises(InputError, match="needs its job_id"):
            writer.put(Sample(device.id, 1.0, 0.0, 0.0, source="calibration"))
        with pytest.raises(InputError, match="source"):
            writer.put(Sample(device.id, 1.0, 0.0, 0.0, source="other"))
        with pytest.raises(InputError, match="finite"):
            writer.put(Sample(device.id, float("nan"), 0.0, 0.0))
    assert writer.handed_over == 0


def test_settled_points_and_record_provenance(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    job = store.jobs.create_job(device.id, "scale", "linear", actor="alice")
    store.jobs.start_job(job.id, actor="alice")
    raw = [
        Sample(
            device.id,
            100.0 * p + i,
            0.1 * p + 1e-4 * (i % 3),
            -0.1 * p,
            None,
            20.0 + 0.01 * i,
            job.id,
            p,
            "calibration",
        )
        for p in range(4)
        for i in range(20)
    ]
    write_samples(store.engine, raw)
    points = store.points.settle_from_samples(
        job.id, device.id, actor="alice", skip_s=5.0, commands={p: (p * 1.0, 0.0) for p in range(4)}
    )
    assert [p.n_samples for p in points] == [15] * 4
    assert points[2].cmd_x_deg == 2.0 and abs(points[2].ch_y_mean + 0.2) < 1e-12
    with store.engine.connect() as conn:
        assert len(job_samples(conn, job.id, point=1)) == 20
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
    store.jobs.succeed_job(job.id, actor="alice")
    assert (
        rec.raw_data["points"] == 4
        and rec.raw_data["samples"] == 80
        and rec.raw_data["job_id"] == job.id
    )
    assert verify(store.engine).ok
    with pytest.raises(IllegalTransition, match="succeeded"):
        # the job no longer runs
        store.points.add_settled_points(job.id, device.id, [], actor="alice")


def test_changed_settled_points_are_reported(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    job = store.jobs.create_job(device.id, "scale", "linear", actor="alice")
    store.jobs.start_job(job.id, actor="alice")
    store.points.add_settled_points(
        job.id,
        device.id,
        [
            {
                "point": p,
                "n_samples": 10,
                "t_start_s": p,
                "t_end_s": p + 1.0,
                "ch_x_mean": p * 0.1,
                "ch_y_mean": 0.0,
            }
            for p in range(3)
        ],
        actor="alice",
    )
    rec = store.records.add_record(
        device.id, "scale", "linear", MODEL, operator="alice", job_id=job.id
    )
    with store.engine.begin() as conn:
        if store.engine.dialect.name == "sqlite":
            conn.exec_driver_sql("DROP TRIGGER trg_settled_points_no_update")
        else:
            conn.exec_driver_sql("ALTER TABLE settled_points DISABLE TRIGGER USER")
        conn.exec_driver_sql("UPDATE settled_points SET ch_x_mean = 0.5 WHERE point = 1")
    assert [(p.row_id, p.kind) for p in verify(store.engine).problems] == [
        (rec.id, "raw_data_changed")
    ]


def test_changed_points_of_a_measurement_an_adopted_version_used_are_reported(
    store: Store, device
) -> None:  # type: ignore[no-untyped-def]
    """A version adopted from a diagnosis that measured more points was fitted on that job's points
    too."""
    jobs = []
    for _ in range(2):
        job = store.jobs.create_job(device.id, "scale", "linear", actor="alice")
        store.jobs.start_job(job.id, actor="alice")
        store.points.add_settled_points(
            job.id,
            device.id,
            [
                {
                    "point": p,
                    "n_samples": 10,
                    "t_start_s": p,
                    "t_end_s": p + 1.0,
                    "ch_x_mean": p * 0.1,
                    "ch_y_mean": 0.0,
                }
                for p in range(3)
            ],
            actor="alice",
        )
        jobs.append(job)
    first, measured = jobs
    rec = store.records.add_record(
        device.id,
        "scale",
        "linear",
        MODEL,
        operator="alice",
        job_id=first.id,
        raw_data={
            "measurement_job_ids": [measured.id],
            "measurement_points_sha256": store.points.points_sha256_by_job([measured.id]),
        },
    )
    assert verify(store.engine).ok
    with store.engine.begin() as conn:
        if store.engine.dialect.name == "sqlite":
            conn.exec_driver_sql("DROP TRIGGER trg_settled_points_no_update")
        else:
            conn.exec_driver_sql("ALTER TABLE settled_points DISABLE TRIGGER USER")
        conn.exec_driver_sql(
            f"UPDATE settled_points SET ch_x_mean = 0.5 WHERE point = 1 AND job_id = {measured.id}"
        )
    problems = verify(store.engine).problems
    assert [(p.row_id, p.kind) for p in problems] == [(rec.id, "raw_data_changed")]
    assert f"measurement job {measured.id}" in problems[0].detail


def _t(days_ago: float) -> float:
    return NOW.timestamp() - days_ago * DAY_S


def test_retention_drops_only_old_monitoring_samples(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    job = store.jobs.create_job(device.id, "scale", "linear", actor="alice")
    old_cal = [
        Sample(device.id, _t(400) + i, 0.0, 0.0, None, None, job.id, 0, "calibration")
        for i in range(50)
    ]
    old_mon = [Sample(device.id, _t(40) + i, 0.0, 0.0) for i in range(300)]
    new_mon = [Sample(device.id, _t(1) + i, 0.0, 0.0) for i in range(70)]
    write_samples(store.engine, old_cal + old_mon + new_mon)
    result = store.retention.apply(
        actor="retention", older_than=dt.timedelta(days=30), policy="drop", now=NOW
    )
    assert result.deleted == 300
    with store.engine.connect() as conn:
        assert count_samples(conn, source="calibration") == 50
        assert count_samples(conn, source="monitoring") == 70
    assert store.audit.events(entity="samples")[0].details["deleted"] == 300


def test_retention_thins_old_monitoring_samples(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    other = store.devices.add_device("NS-25/E2", "SN2", "dut", actor="a")
    job = store.jobs.create_job(device.id, "scale", "linear", actor="alice")
    start = (int(_t(40)) // 60) * 60.0  # minute-aligned, so the buckets are exact
    # 5 min each
    old = [Sample(d, start + i * 0.5, 0.0, 0.0) for d in (device.id, other.id) for i in range(600)]
    cal = [
        Sample(device.id, start + i * 0.5, 0.0, 0.0, None, None, job.id, 1, "calibration")
        for i in range(600)
    ]
    new = [Sample(device.id, _t(0.5) + i, 0.0, 0.0) for i in range(100)]
    write_samples(store.engine, old + cal + new)
    result = store.retention.apply(
        actor="retention",
        older_than=dt.timedelta(days=30),
        policy="thin",
        thin_interval_s=60.0,
        now=NOW,
    )
    assert result.kept_thinned == 10 and result.deleted == 1190
    with store.engine.connect() as conn:
        assert count_samples(conn, source="calibration") == 600
        assert count_samples(conn, device_id=device.id, source="monitoring") == 5 + 100
        kept = (
            conn.execute(
                sa.text(
                    "SELECT t_s FROM samples WHERE device_id = :d AND source = 'monitoring' AND "
                    "t_s < :c ORDER BY t_s"
                ),
                {"d": other.id, "c": _t(30)},
            )
            .scalars()
            .all()
        )
    assert kept == [start + 60.0 * k for k in range(5)]


def test_retention_refuses_nonsense(store: Store) -> None:
    with pytest.raises(InputError):
        store.retention.apply(actor="r", older_than=dt.timedelta(days=-1))
    with pytest.raises(InputError):
        store.retention.apply(actor="r", older_than=dt.timedelta(days=1), policy="shred")


def test_put_racing_close_is_refused_not_lost(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    """A producer still handing over when another thread closes the writer is told so; nothing
    vanishes."""
    writer = SampleWriter(store.engine, capacity=100, batch_size=10)

    def samples():  # type: ignore[no-untyped-def]
        closer = threading.Thread(target=writer.close)  # closes while this put_many is under way
        closer.start()
        closer.join()
        yield Sample(device.id, 1.0, 0.0, 0.0)

    with pytest.raises(RuntimeError, match="closed"):
        writer.put_many(samples())
    assert writer.handed_over == 0 and writer.pending == 0
    assert count(store.engine, "samples") == 0


def test_unavailable_database_fails_whole_batches_not_row_by_row(
    store: Store, device, db_url: str
) -> None:  # type: ignore[no-untyped-def]
    """When the retries run out the batch is reported as not written; retrying each row would stall
    the writer."""
    if store.engine.dialect.name == "sqlite":
        engine = make_engine(db_url, busy_timeout_ms=20)
    else:
        url = sa.make_url(db_url)
        engine = make_engine(
            url.update_query_dict({"options": f"{url.query['options']} -clock_timeout=20ms"})
        )
    holder = _hold_write_lock(store.engine)
    writer = SampleWriter(engine, capacity=200, batch_size=100, retry_for_s=0.2)
    attempts = []
    transactions = writer._engine.begin

    def begin():  # type: ignore[no-untyped-def]
        attempts.append(1)
        return transactions()

    writer._engine = SimpleNamespace(begin=begin)
    try:
        writer.put_many([Sample(device.id, float(i), 0.0, 0.0) for i in range(200)])
        with pytest.raises(SampleWriteError, match="200 samples"):
            writer.flush(timeout=60)
    finally:
        holder.rollback()
        holder.close()
        with pytest.raises(SampleWriteError):
            writer.close()
        engine.dispose()
    assert writer.committed == 0 and len(writer.rejected) == 200
    assert len(attempts) < 100  # a few attempts per batch, not one per sample


@pytest.mark.parametrize(
    ("sample", "match"),
    [
        # SQLite would refuse it late, PostgreSQL store it
        (Sample(1, 1.0, float("nan"), 0.0), "ch_x"),
        (Sample(1, 1.0, 0.0, float("-inf")), "ch_y"),
        (Sample(1, 1.0, 0.0, 0.0, float("nan")), "ch_z"),  # SQLite would store NULL, PostgreSQL NaN
        (Sample(1, 1.0, 0.0, 0.0, None, float("inf")), "temp_c"),
        (Sample(1, 1.0, "0.1", 0.0), "ch_x"),  # SQLite would keep the text in a REAL column
        (Sample("1", 1.0, 0.0, 0.0), "device_id"),
        (Sample(None, 1.0, 0.0, 0.0), "device_id"),
        (Sample(1, True, 0.0, 0.0), "t_s"),
    ],
)
def test_non_numeric_or_non_finite_values_are_refused_at_the_producer(
    store: Store, device, sample, match
) -> None:  # type: ignore[no-untyped-def]
    sample = sample._replace(device_id=device.id) if sample.device_id == 1 else sample
    with SampleWriter(store.engine, capacity=10, batch_size=5) as writer:
        with pytest.raises(InputError, match=match):
            writer.put(sample)
        with pytest.raises(InputError, match=match):
            writer.put_many([Sample(device.id, 0.5, 0.0, 0.0), sample])
    assert writer.handed_over == 0 and count(store.engine, "samples") == 0


def test_latest_samples_refuses_a_negative_count(store: Store, device) -> None:  # type: ignore[no-untyped-def]
    write_samples(store.engine, [Sample(device.id, float(i), 0.0, 0.0) for i in range(5)])
    with store.engine.connect() as conn:
        assert latest_samples(conn, device.id, 0) == []
        with pytest.raises(InputError, match="n=-1"):
            # SQLite would read the whole table, PostgreSQL fail
            latest_samples(conn, device.id, -1)


@pytest.mark.parametrize("skip_s", [float("nan"), -1.0, "5"])
def test_settling_time_must_be_a_non_negative_number(store: Store, device, skip_s) -> None:  # type: ignore[no-untyped-def]
    job = store.jobs.create_job(device.id, "scale", "linear", actor="alice")
    store.jobs.start_job(job.id, actor="alice")
    write_samples(
        store.engine,
        [
            Sample(device.id, float(i), 0.0, 0.0, None, None, job.id, 0, "calibration")
            for i in range(10)
        ],
    )
    with pytest.raises(InputError, match="skip_s"):
        store.points.settle_from_samples(job.id, device.id, actor="alice", skip_s=skip_s)
    assert store.points.settled_points(job.id) == []


def test_retention_refuses_a_naive_now_and_an_age_that_is_not_a_timedelta(
    store: Store, device
) -> None:  # type: ignore[no-untyped-def]
    write_samples(store.engine, [Sample(device.id, _t(40), 0.0, 0.0)])
    with pytest.raises(InputError, match="timezone"):  # a naive time would be read as local time
        store.retention.apply(
            actor="r", older_than=dt.timedelta(days=30), now=NOW.replace(tzinfo=None)
        )
    with pytest.raises(InputError, match="timedelta"):
        store.retention.apply(actor="r", older_than=30)  # type: ignore[arg-type]
    with store.engine.connect() as conn:
        assert count_samples(conn) == 1
