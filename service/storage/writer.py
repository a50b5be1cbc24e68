"""SampleWriter: samples from acquisition threads to the database in batches, off their thread.

Producers call `put`/`put_many`; a background thread takes up to `batch_size` samples at a
time from a bounded queue and commits each batch in one transaction. When the database falls
behind, the queue fills and `put` blocks (back-pressure) for at most `put_timeout_s`, then raises
`BackPressureTimeout`: acquisition learns that it is losing data instead of memory growing.

Loss bound. A sample is *handed over* when `put`/`put_many` has returned for it. At any moment
the handed-over samples not yet committed are those in the queue (at most `capacity`) plus the
batch being written (at most `batch_size`). So if the process is killed (SIGKILL, a crash)
at most `capacity + batch_size` handed-over samples are lost, and the committed ones are exactly
the oldest handed-over ones (batches commit in order). A power loss may also roll back the last
commits on SQLite with synchronous=NORMAL (see docs/storage.md). `close()` (also run at interpreter
exit) and `flush()` lose nothing.

Database outage. While the database is away (see `service.storage.outage`) the writer keeps its
batches, in order, and tries again with back-off until it answers; nothing handed over is given up,
however long the outage (only `close()` gives up, once the outage has lasted `outage_s`). Producers
are not held meanwhile: `put_many` takes what fits in the queue and refuses the newest samples
beyond it, counting them in `dropped` (it returns how many it took). A batch tried again after a
failure whose outcome is unknown (its COMMIT sent, the answer lost) is written only if it is not
already stored, so no sample is stored twice.
"""

from __future__ import annotations

import atexit
import collections
import logging
import queue
import threading
import time
from collections.abc import Iterable, Sequence

import sqlalchemy as sa

from service.storage.engine import write_engine
from service.storage.errors import BackPressureTimeout, SampleWriteError
from service.storage.outage import DatabaseState, unreachable
from service.storage.samples import Sample, check_samples, insert_samples, insert_samples_once

log = logging.getLogger(__name__)


class _SampleQueue(queue.Queue):  # type: ignore[type-arg]
    """A bounded queue.Queue of sample chunks whose size, and bound, count samples, not chunks."""

    def _init(self, maxsize: int) -> None:
        self.queue: collections.deque[Sequence[Sample]] = collections.deque()
        self.samples = 0
        self.closed = False

    def _qsize(self) -> int:
        return self.samples

    def close(self) -> None:
        """Take no more chunks; producers waiting for room are released and refused."""
        with self.mutex:
            self.closed = True
            self.not_full.notify_all()
            self.not_empty.notify_all()

    def drained(self) -> bool:
        """Closed and empty: nothing can arrive any more."""
        with self.mutex:
            return self.closed and not self.samples

    def put_what_fits(self, chunk: Sequence[Sample]) -> int:
        """Without waiting: as many of the chunk's first samples as there is room for (0 if
        closed)."""
        with self.not_full:
            room = 0 if self.closed else max(0, min(len(chunk), self.maxsize - self.samples))
            if room:
                self.queue.append(chunk[:room])
                self.samples += room
                self.not_empty.notify()
            return room

    def put_chunk(self, chunk: Sequence[Sample], timeout: float) -> bool:
        """Block until the whole chunk fits (len(chunk) <= maxsize), or raise queue.Full; False if
        closed."""
        deadline = time.monotonic() + timeout
        with self.not_full:
            while not self.closed and self.samples + len(chunk) > self.maxsize:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise queue.Full
                self.not_full.wait(remaining)
            if self.closed:
                return False
            self.queue.append(chunk)
            self.samples += len(chunk)
            self.not_empty.notify()
            return True

    def get_batch(self, max_n: int, timeout: float) -> list[Sample]:
        """Up to max_n samples in put order; [] if none arrived within the timeout."""
        with self.not_empty:
            if not self.samples:
                self.not_empty.wait(timeout)
            batch: list[Sample] = []
            while self.queue and len(batch) < max_n:
                chunk = self.queue[0]
                room = max_n - len(batch)
                if len(chunk) <= room:
                    self.queue.popleft()
                    batch.extend(chunk)
                else:
                    batch.extend(chunk[:room])
                    self.queue[0] = chunk[room:]
            self.samples -= len(batch)
            if batch:
                self.not_full.notify_all()
            return batch


class SampleWriter:
    def __init__(
        self,
        engine: sa.Engine,
        *,
        capacity: int = 50_000,
        batch_size: int = 5_000,
        put_timeout_s: float = 5.0,
        validate: bool = True,
        retry_for_s: float = 30.0,
        database: DatabaseState | None = None,
    ) -> None:
        if batch_size < 1 or capacity < batch_size:
            raise ValueError("need 1 <= batch_size <= capacity")
        self.capacity = capacity
        self.batch_size = batch_size
        self.put_timeout_s = put_timeout_s
        self.validate = validate
        self.retry_for_s = retry_for_s
        self._engine = write_engine(engine)
        # shared with the daemon's other writers when given: /health and /metrics read it
        self.database = database or DatabaseState(
            str(engine.url.render_as_string(hide_password=True))
        )
        self.dropped = 0  # samples refused while the database was away and the queue full
        self._queue = _SampleQueue(capacity)
        self._progress = threading.Condition()
        self.handed_over = 0
        self.committed = 0
        self.rejected: list[tuple[Sample, str]] = []
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="tiltlab-sample-writer", daemon=True)
        self._thread.start()
        atexit.register(self.close)

    @classmethod
    def from_settings(  # type: ignore[no-untyped-def]
        cls, engine: sa.Engine, settings, database: DatabaseState | None = None
    ) -> SampleWriter:
        return cls(
            engine,
            capacity=settings.sample_queue_capacity,
            batch_size=settings.sample_batch_size,
            put_timeout_s=settings.sample_put_timeout_s,
            database=database
            or DatabaseState(engine.url.render_as_string(hide_password=True), settings.db_outage_s),
        )

    @property
    def loss_bound(self) -> int:
        """Most handed-over samples a hard kill can lose."""
        return self.capacity + self.batch_size

    def put(self, sample: Sample) -> bool:
        return self.put_many((sample,)) == 1

    @property
    def queued(self) -> int:
        """Samples in the queue (not yet taken into a batch)."""
        return self._queue.qsize()

    def put_many(self, samples: Iterable[Sample]) -> int:
        """Hand samples over; returns how many were taken. Blocks while the queue is full, up to
        put_timeout_s per batch-sized chunk; while the database is away it does not wait: the
        samples beyond the queue's room are refused and counted in `dropped`."""
        if self._queue.closed:
            raise RuntimeError("SampleWriter is closed")
        rows = samples if isinstance(samples, list) else list(samples)
        if self.validate:
            check_samples(rows)
        accepted = 0
        for i in range(0, len(rows), self.batch_size):
            chunk = rows[i : i + self.batch_size]
            if not self.database.up:
                took = self._put_what_fits(chunk, accepted, len(rows))
                accepted += took
                if took < len(chunk):
                    return accepted
                continue
            self._put_waiting(chunk, accepted, len(rows))
            accepted += len(chunk)
        return accepted

    def _put_what_fits(self, chunk: list[Sample], accepted: int, total: int) -> int:
        """While the database is away a producer does not wait: the samples the queue has no room
        for are refused and counted in `dropped`. Returns how many of the chunk were taken."""
        took = self._queue.put_what_fits(chunk)
        with self._progress:
            self.handed_over += took
            if took < len(chunk):
                self.dropped += total - (accepted + took)
        if took < len(chunk):
            if self._queue.closed:
                raise RuntimeError("SampleWriter is closed")
            log.warning(
                "database away and the sample queue full: %d samples refused",
                total - (accepted + took),
            )
        return took

    def _put_waiting(self, chunk: list[Sample], accepted: int, total: int) -> None:
        """While the database answers a producer waits for room, up to put_timeout_s per chunk:
        the back pressure of a database not keeping up."""
        try:
            if not self._queue.put_chunk(chunk, self.put_timeout_s):
                raise RuntimeError(
                    f"SampleWriter is closed; {accepted} of these {total} samples were "
                    "accepted, the rest were not"
                )
        except queue.Full:
            raise BackPressureTimeout(
                f"sample queue full for {self.put_timeout_s} s: the database is not keeping up;"
                f" {accepted} of these {total} samples were accepted, the rest were not"
            ) from None
        with self._progress:
            self.handed_over += len(chunk)

    def flush(self, timeout: float | None = None) -> None:
        """Wait until every sample handed over so far is committed (or rejected)."""
        with self._progress:
            target = self.handed_over
            done = self._progress.wait_for(
                lambda: (
                    self.committed + len(self.rejected) >= target or not self._thread.is_alive()
                ),
                timeout,
            )
        if not done:
            raise TimeoutError(
                f"flush: {target - self.committed} samples still uncommitted after {timeout} s"
            )
        self._raise_rejected()

    def close(self, timeout: float | None = None) -> None:
        """Write everything handed over, stop the thread. Idempotent."""
        if self._closed:
            return
        self._queue.close()
        self._thread.join(timeout)
        if self._thread.is_alive():
            raise TimeoutError(
                f"close: writer still busy after {timeout} s; {self.pending} samples pending"
            )
        self._closed = True
        atexit.unregister(self.close)
        self._raise_rejected()
        if self.pending:
            raise SampleWriteError(f"writer stopped with {self.pending} samples not written")

    @property
    def pending(self) -> int:
        with self._progress:
            return self.handed_over - self.committed - len(self.rejected)

    def __enter__(self) -> SampleWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _raise_rejected(self) -> None:
        if self.rejected:
            sample, reason = self.rejected[0]
            raise SampleWriteError(
                f"{len(self.rejected)} samples were refused by the database; first: {sample} "
                f"({reason})"
            )

    def _run(self) -> None:
        while True:
            batch = self._queue.get_batch(self.batch_size, timeout=0.05)
            if batch:
                self._write(batch)
            elif self._queue.drained():
                return

    def _write(self, batch: list[Sample]) -> None:
        deadline = time.monotonic() + self.retry_for_s
        delay = 0.05
        # once a try failed, the batch may be stored already (a COMMIT whose answer was lost)
        tried = False
        while True:
            try:
                with self._engine.begin() as conn:
                    (insert_samples_once if tried else insert_samples)(conn, batch)
                self.database.back()
                self._count_committed(len(batch))
                return
            except sa.exc.OperationalError as exc:  # locked or unreachable: worth waiting for
                tried = True
                next_delay = self._wait_to_retry(exc, deadline, delay)
                if next_delay is None:
                    # Not the rows' fault: trying them one by one would only wait out the same lock
                    # or outage once per row while the queue fills.
                    log.error("sample batch failed after retries: %s", exc)
                    self._reject(batch, exc)
                    return
                delay = next_delay
            except Exception as exc:  # noqa: BLE001 - a bad row in the batch: find it, keep the others
                # an earlier try may have stored it: row by row would store those rows twice
                if tried:
                    self._reject(batch, exc)
                    return
                log.warning("sample batch refused (%s); writing it row by row", _reason(exc))
                break
        self._write_row_by_row(batch)

    def _wait_to_retry(
        self, exc: sa.exc.OperationalError, deadline: float, delay: float
    ) -> float | None:
        """After a batch met a locked or unreachable database: waits `delay` and returns the next
        delay, or None when the batch is given up (the lock outlasted the retries, or the writer is
        closing and the outage has outlasted outage_s)."""
        if unreachable(exc):
            # The database is away: the batch waits for it (in order, the queue behind it),
            # given up only when the writer is being closed and the outage outlasts
            # outage_s.
            self.database.away(exc)
            if not (self._queue.closed and self.database.away_for_s() >= self.database.outage_s):
                time.sleep(delay)
                return min(delay * 2, 2.0)
        if time.monotonic() >= deadline or unreachable(exc):
            return None
        time.sleep(delay)
        return min(delay * 2, 1.0)

    def _write_row_by_row(self, batch: list[Sample]) -> None:
        """A batch the database refused, written row by row: the bad rows are rejected, the others
        kept."""
        for row in batch:
            try:
                with self._engine.begin() as conn:
                    insert_samples(conn, [row])
                self._count_committed(1)
            except Exception as exc:  # noqa: BLE001 - recorded, and raised to the producer at flush/close
                with self._progress:
                    self.rejected.append((row, _reason(exc)))
                    self._progress.notify_all()

    def _count_committed(self, count: int) -> None:
        """Samples committed, counted and told to whoever waits in flush."""
        with self._progress:
            self.committed += count
            self._progress.notify_all()

    def _reject(self, batch: list[Sample], exc: BaseException) -> None:
        """A whole batch refused with the reason, raised to the producer at flush/close."""
        with self._progress:
            self.rejected.extend((row, _reason(exc)) for row in batch)
            self._progress.notify_all()


def _reason(exc: BaseException) -> str:
    orig = getattr(exc, "orig", None) or exc
    lines = str(orig).strip().splitlines()
    return lines[0] if lines else type(orig).__name__
