"""Storage benchmark: sustained sample ingest into SQLite, and reading the latest 1,000 samples.

    python benchmarks/bench_storage.py                    # full run (builds a 10M-row table)
    python benchmarks/bench_storage.py --rows 1000000     # quicker latency table
    python benchmarks/bench_storage.py --postgres postgresql+psycopg://root@127.0.0.1:5432/test

Ingest compares, on the same schema (created by the migrations, indexes and triggers included),
the same pragmas and the same pre-generated samples:
  * plain sqlite3 `executemany`, one transaction per batch (the reference),
  * the storage layer's bulk path `insert_samples` (driver executemany on SQLAlchemy's connection),
  * `SampleWriter` end to end: a producer thread hands samples over, the writer thread commits.
Latency: `latest_samples(conn, device, 1000)` through SQLAlchemy on a table of --rows rows.
"""

from __future__ import annotations

import argparse
import os
import random
import sqlite3
import statistics
import sys
import threading
import time
import uuid
from pathlib import Path

import sqlalchemy as sa

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.storage import (
    Sample,
    SampleWriter,
    Store,
    insert_samples,
    latest_samples,
    make_engine,
    upgrade,
)  # noqa: E402
from service.storage.engine import write_engine  # noqa: E402
from service.storage.samples import COLUMNS  # noqa: E402

DEVICES = 4
T0 = 1.77e9


def make_samples(n: int) -> list[Sample]:
    return [
        Sample(
            1 + i % DEVICES,
            T0 + i * 1e-3,
            1e-4 * (i % 997),
            -1e-4 * (i % 991),
            None,
            21.0 + 1e-5 * (i % 101),
        )
        for i in range(n)
    ]


def fresh_db(directory: Path, name: str) -> tuple[Path, sa.Engine]:
    path = directory / f"{name}.db"
    for suffix in ("", "-wal", "-shm"):
        Path(f"{path}{suffix}").unlink(missing_ok=True)
    engine = make_engine(f"sqlite:///{path}")
    upgrade(engine)
    store = Store(engine)
    for d in range(DEVICES):
        store.devices.add_device("NS-25/E2", f"BENCH{d}", "dut", actor="bench")
    return path, engine


def plain_sqlite3(path: Path, rows: list[Sample], batch: int) -> float:
    conn = sqlite3.connect(path, isolation_level=None)
    for pragma in (
        "journal_mode=WAL",
        "foreign_keys=ON",
        "synchronous=NORMAL",
        "busy_timeout=5000",
    ):
        conn.execute(f"PRAGMA {pragma}")
    sql = f"INSERT INTO samples ({', '.join(COLUMNS)}) VALUES ({', '.join('?' * len(COLUMNS))})"
    t = time.perf_counter()
    for i in range(0, len(rows), batch):
        conn.execute("BEGIN")
        conn.executemany(sql, rows[i : i + batch])
        conn.execute("COMMIT")
    elapsed = time.perf_counter() - t
    conn.close()
    return elapsed


def storage_bulk(engine: sa.Engine, rows: list[Sample], batch: int) -> float:
    weng = write_engine(engine)
    t = time.perf_counter()
    for i in range(0, len(rows), batch):
        with weng.begin() as conn:
            insert_samples(conn, rows[i : i + batch])
    return time.perf_counter() - t


def sample_writer(engine: sa.Engine, rows: list[Sample], batch: int, chunk: int = 1000) -> float:
    writer = SampleWriter(engine, capacity=10 * batch, batch_size=batch, put_timeout_s=60)

    def produce() -> None:
        for i in range(0, len(rows), chunk):
            writer.put_many(rows[i : i + chunk])

    t = time.perf_counter()
    producer = threading.Thread(target=produce)
    producer.start()
    producer.join()
    writer.close()
    elapsed = time.perf_counter() - t
    assert writer.committed == len(rows)
    return elapsed


def count_rows(engine: sa.Engine) -> int:
    with engine.connect() as conn:
        return int(conn.execute(sa.text("SELECT count(*) FROM samples")).scalar_one())


def bench_ingest(directory: Path, n: int, batch: int, repeats: int) -> None:
    rows = make_samples(n)
    results: dict[str, list[float]] = {
        "plain sqlite3 executemany": [],
        "storage insert_samples": [],
        "SampleWriter": [],
    }
    for r in range(repeats):
        for name in results:
            path, engine = fresh_db(directory, f"ingest-{r}")
            if name.startswith("plain"):
                elapsed = plain_sqlite3(path, rows, batch)
            elif name.startswith("storage"):
                elapsed = storage_bulk(engine, rows, batch)
            else:
                elapsed = sample_writer(engine, rows, batch)
            assert count_rows(engine) == n
            engine.dispose()
            results[name].append(n / elapsed)
            print(
                f"  run {r + 1}: {name:28s} {n / elapsed:>10,.0f} samples/s ({elapsed:.2f} s)",
                flush=True,
            )
    ref = statistics.median(results["plain sqlite3 executemany"])
    print(f"\nIngest into SQLite, {n:,} samples, batches of {batch:,}, median of {repeats} runs:")
    for name, rates in results.items():
        med = statistics.median(rates)
        print(f"  {name:28s} {med:>10,.0f} samples/s   {med / ref:5.2f} x plain sqlite3")


def build_big(directory: Path, rows: int) -> Path:
    path = directory / f"latest-{rows}.db"
    if path.exists():
        engine = make_engine(f"sqlite:///{path}")
        if count_rows(engine) == rows:
            engine.dispose()
            print(f"  reusing {path} ({rows:,} rows)")
            return path
        engine.dispose()
    path, engine = fresh_db(directory, f"latest-{rows}")
    engine.dispose()
    t = time.perf_counter()
    conn = sqlite3.connect(path, isolation_level=None)
    conn.execute("PRAGMA journal_mode=WAL")
    conn.execute("PRAGMA synchronous=OFF")
    conn.execute("PRAGMA cache_size=-1000000")
    # Bulk load without the secondary indexes, then build them with the migration's definitions.
    index_sql = [
        s
        for (s,) in conn.execute(
            "SELECT sql FROM sqlite_master WHERE type='index' AND tbl_name='samples' AND sql IS "
            "NOT NULL"
        )
    ]
    for (name,) in conn.execute(
        "SELECT name FROM sqlite_master WHERE type='index' AND tbl_name='samples' AND sql IS NOT "
        "NULL"
    ).fetchall():
        conn.execute(f"DROP INDEX {name}")
    step = 2_000_000
    for start in range(0, rows, step):
        stop = min(rows, start + step)
        conn.execute("BEGIN")
        conn.execute(
            f"""INSERT INTO samples ({", ".join(COLUMNS)})
            WITH RECURSIVE c(i) AS
                (SELECT {start} UNION ALL SELECT i + 1 FROM c WHERE i < {stop - 1})
            SELECT 1 + i % {DEVICES}, {T0} + i * 0.001, (i % 997) * 1e-4, -(i % 991) * 1e-4, NULL,
                   21.0 + (i % 101) * 1e-5, NULL, NULL, 'monitoring' FROM c"""
        )
        conn.execute("COMMIT")
        print(f"  loaded {stop:,} rows ({time.perf_counter() - t:.0f} s)", flush=True)
    for sql in index_sql:
        conn.execute(sql)
    conn.execute("ANALYZE")
    # as the service's auto-checkpoint would, eventually
    conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    conn.close()
    print(f"  built {path} with {rows:,} rows in {time.perf_counter() - t:.0f} s")
    return path


def bench_latest(directory: Path, rows: int, queries: int) -> None:
    path = build_big(directory, rows)
    raw = sqlite3.connect(path)
    raw.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    sql = (
        f"SELECT {', '.join(COLUMNS)} FROM samples WHERE device_id = ? ORDER BY t_s DESC LIMIT 1000"
    )
    raw_times = []
    for i in range(queries):
        t = time.perf_counter()
        raw.execute(sql, (1 + i % DEVICES,)).fetchall()
        raw_times.append((time.perf_counter() - t) * 1e3)
    raw.close()
    raw_times.sort()
    engine = make_engine(f"sqlite:///{path}")
    rng = random.Random(1)
    with engine.connect() as conn:
        first_t = time.perf_counter()
        first = latest_samples(conn, 1, 1000)
        first_ms = (time.perf_counter() - first_t) * 1e3
        assert len(first) == 1000 and first[0].t_s > first[-1].t_s
        for _ in range(20):  # warm the connection's page cache, as a running service's would be
            latest_samples(conn, rng.randint(1, DEVICES), 1000)
        times, cpu = [], []
        for _ in range(queries):
            device = rng.randint(1, DEVICES)
            t, c = time.perf_counter(), time.process_time()
            got = latest_samples(conn, device, 1000)
            times.append((time.perf_counter() - t) * 1e3)
            cpu.append((time.process_time() - c) * 1e3)
            assert len(got) == 1000
        plan = conn.exec_driver_sql(
            "EXPLAIN QUERY PLAN SELECT * FROM samples WHERE device_id = 1 ORDER BY t_s DESC LIMIT "
            "1000"
        ).all()
    engine.dispose()
    times.sort()
    print(
        f"\nLatest 1,000 samples of a device, table of {rows:,} rows ({DEVICES} devices), "
        f"{queries} queries:"
    )
    print(
        f"  first query {first_ms:.2f} ms; median {statistics.median(times):.2f} ms, "
        f"p95 {times[int(0.95 * len(times))]:.2f} ms, max {times[-1]:.2f} ms; "
        f"CPU time per query: median {statistics.median(cpu):.2f} ms"
    )
    print(f"  plan: {' | '.join(str(p[-1]) for p in plan)}")
    print(
        f"  (same query in plain sqlite3: median {statistics.median(raw_times):.2f} ms, "
        f"p95 {raw_times[int(0.95 * len(raw_times))]:.2f} ms)"
    )


def bench_postgres(url: str, n: int, batch: int) -> None:
    admin = make_engine(url)
    schema = f"bench_{uuid.uuid4().hex[:8]}"
    with admin.begin() as conn:
        conn.execute(sa.text(f"CREATE SCHEMA {schema}"))
    try:
        engine = make_engine(
            sa.make_url(url).update_query_dict({"options": f"-csearch_path={schema}"})
        )
        upgrade(engine)
        store = Store(engine)
        for d in range(DEVICES):
            store.devices.add_device("NS-25/E2", f"BENCH{d}", "dut", actor="bench")
        rows = make_samples(n)
        elapsed = storage_bulk(engine, rows, batch)
        with engine.begin() as conn:
            conn.execute(sa.text("DELETE FROM samples"))
        elapsed_w = sample_writer(engine, rows, batch)
        print(f"\nPostgreSQL ({n:,} samples, batches of {batch:,}, COPY):")
        print(f"  storage insert_samples {n / elapsed:>10,.0f} samples/s")
        print(f"  SampleWriter           {n / elapsed_w:>10,.0f} samples/s")
        engine.dispose()
    finally:
        with admin.begin() as conn:
            conn.execute(sa.text(f"DROP SCHEMA {schema} CASCADE"))
        admin.dispose()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dir", default=os.environ.get("TMPDIR", "/tmp") + "/tiltlab-bench")
    p.add_argument("--samples", type=int, default=1_000_000)
    p.add_argument("--batch", type=int, default=5_000)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--rows", type=int, default=10_000_000)
    p.add_argument("--queries", type=int, default=500)
    p.add_argument(
        "--postgres", default=None, help="also measure ingest into PostgreSQL at this URL"
    )
    p.add_argument("--skip-ingest", action="store_true")
    p.add_argument("--skip-latest", action="store_true")
    args = p.parse_args()
    directory = Path(args.dir)
    directory.mkdir(parents=True, exist_ok=True)
    print(
        f"python {sys.version.split()[0]}, sqlite {sqlite3.sqlite_version}, sqlalchemy "
        f"{sa.__version__}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}, files "
        f"in {directory}",
        flush=True,
    )
    if not args.skip_ingest:
        bench_ingest(directory, args.samples, args.batch, args.repeats)
    if args.postgres:
        bench_postgres(args.postgres, args.samples, args.batch)
    if not args.skip_latest:
        bench_latest(directory, args.rows, args.queries)


if __name__ == "__main__":
    main()
