"""A job's measured point is stored whole or not at all. A write that fails part-way (the disk
fills between the raw samples and the second instrument's settled means) leaves nothing of the
point, so the resumed job measures it again whole and `db verify` finds every settled point's
samples as it hashed them. A point half stored by an earlier daemon (one instrument's settled
means) keeps that half: measuring it again adds only what it lacks."""

from __future__ import annotations

import sqlite3

import pytest
import sqlalchemy as sa

from service.jobs.points import store_point
from service.storage.engine import make_engine
from service.storage.migrate import upgrade
from service.storage.samples import Sample, count_samples, write_samples
from service.storage.store import Store
from service.storage.store.points import PointsRepo
from service.storage.verify import verify


@pytest.fixture
def bench(tmp_path):
    engine = make_engine(f"sqlite:///{tmp_path / 'points.db'}")
    upgrade(engine)
    store = Store(engine)
    b = store.devices.ensure_bench("b1", actor="t")
    ref = store.devices.add_device("R", "1", "reference_sensor", actor="t", bench_id=b.id)
    meas = store.devices.add_device("M", "1", "measurement_sensor", actor="t", bench_id=b.id)
    job = store.jobs.create_job(meas.id, "stage", "kinematic", actor="t")
    store.jobs.start_job(job.id, actor="t")
    yield store, job.id, (ref.id, meas.id)
    engine.dispose()


def measured(job_id: int, devices: tuple[int, ...], index: int, t0: float, n: int = 5):
    """One measurement of a point: n samples of each instrument from bench time t0, and their
    settled means."""
    samples = [
        Sample(device, t0 + 0.1 * i + 0.01 * k, 0.1 * index, -0.05, None, 21.5, job_id, index,
               "calibration")
        for k, device in enumerate(devices)
        for i in range(n)
    ]  # fmt: skip
    settled = {
        device: {
            "point": index,
            "cmd_x_deg": float(index),
            "cmd_y_deg": 0.0,
            "n_samples": n,
            "t_start_s": t0,
            "t_end_s": t0 + 0.1 * (n - 1),
            "ch_x_mean": 0.1 * index,
            "ch_y_mean": -0.05,
            "ch_x_std": 0.0,
            "ch_y_std": 0.0,
            "temp_c_mean": 21.5,
        }
        for device in devices
    }
    return samples, settled


def samples_at(store: Store, job_id: int) -> int:
    with store.engine.connect() as conn:
        return count_samples(conn, job_id=job_id)


def test_a_write_that_fails_part_way_leaves_nothing_and_the_point_is_measured_again(
    bench, monkeypatch
):
    store, job_id, devices = bench
    store_point(store, job_id, 0, *measured(job_id, devices, 0, 1000.0))
    add = PointsRepo._add
    calls = []

    def full_at_second_instrument(self, session, job, device, points, actor):
        calls.append(device)
        if len(calls) == 2:
            raise sa.exc.OperationalError(
                "INSERT", {}, sqlite3.OperationalError("database or disk is full")
            )
        return add(self, session, job, device, points, actor)

    monkeypatch.setattr(PointsRepo, "_add", full_at_second_instrument)
    with pytest.raises(sa.exc.OperationalError, match="disk is full"):
        store_point(store, job_id, 1, *measured(job_id, devices, 1, 1010.0))
    monkeypatch.setattr(PointsRepo, "_add", add)
    # nothing of point 1: neither its samples nor the first instrument's settled means
    assert {p.point for p in store.points.settled_points(job_id)} == {0}
    assert samples_at(store, job_id) == 10
    # measured again (new samples) on resume: stored whole, and every hash holds
    store_point(store, job_id, 1, *measured(job_id, devices, 1, 1020.0))
    assert sorted((p.point, p.device_id) for p in store.points.settled_points(job_id)) == sorted(
        (i, d) for i in (0, 1) for d in devices
    )
    assert samples_at(store, job_id) == 20
    report = verify(store.engine)
    assert report.ok and report.sample_points_checked == 4, "\n".join(report.lines())


def test_a_half_stored_point_keeps_its_half_and_gains_only_what_it_lacks(bench):
    store, job_id, devices = bench
    ref, meas = devices
    # what an earlier daemon could leave: both instruments' samples, the reference's settled means
    samples, settled = measured(job_id, devices, 0, 1000.0)
    write_samples(store.engine, samples)
    store.points.add_settled_points(job_id, ref, [settled[ref]], actor="daemon")
    # the resumed job measures the point again: the reference's new samples are not added to its
    # stored point's, the measurement sensor's settled means are
    store_point(store, job_id, 0, *measured(job_id, devices, 0, 1010.0))
    with store.engine.connect() as conn:
        assert count_samples(conn, job_id=job_id, device_id=ref) == 5
    assert sorted(p.device_id for p in store.points.settled_points(job_id)) == sorted(devices)
    report = verify(store.engine)
    assert report.ok and report.sample_points_checked == 2, "\n".join(report.lines())
