"""The live reading stream of a bench: one producer builds each message once and fans it out.

The producer wakes on the bench clock, takes the measurement sensor's readings that arrived since
it last looked (memory, no I/O), and for each new reading builds one message (raw readings, the
corrected table tilt through the active record, stage pose, temperature), serialises it once, keeps
it in a ring buffer (history for snapshots) and offers it to every client whose rate makes it due.
Each client has a bounded queue: a full queue drops the message (counted; a `dropped` message
follows when room returns), so a slow client never slows the producer, the bench or the other
clients. A client whose queue stays full for `slow_close_s` real seconds is told to go (close 1013).
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import json
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, SupportsFloat

import numpy as np
from numpy.typing import NDArray

from service.bench.corrected import (
    MIN_CORRECTION_GAP_S,
    CalibrationInUse,
    CorrectedTilt,
    ReferenceTableTilt,
    calibration_json,
    corrected_once,
    from_expanded,
    in_calibrated_range,
    reference_tilt,
    sensor_temp_c,
    stale_after_s,
)
from service.bench.runtime import SENSOR_ROLES, BenchRuntime
from service.instruments.base import Reading
from service.streams.messages import (
    DroppedMessage,
    HistoryReading,
    ReadingMessage,
    SensorTilt,
    SnapshotHead,
    SnapshotMessage,
    StageTilt,
)

log = logging.getLogger("tiltlab.streams")

HISTORY_MAX_S = 3600.0  # the longest history a snapshot may ask for (bench seconds)
HISTORY_DEFAULT_S = 60.0
MIN_WAKE_S = 0.004  # the producer wakes at most 250 times a real second (a sped-up simulation)
CLOSE_SLOW = 1013  # try again later: the client could not take the messages
CLOSE_GOING_AWAY = 1001

# History ring columns (NaN for "none").
_COLS = (
    "bench_s",
    "epoch",
    "mx",
    "my",
    "rx",
    "ry",
    "tx",
    "ty",
    "ux",
    "uy",
    "table",
    "sx",
    "sy",
    "moving",
    "stage",
    "temp",
    "kx",
    "ky",
    "coverage",
    "in_range",
    "rtx",
    "rty",
)
_C = {name: i for i, name in enumerate(_COLS)}


def utc_text(t: dt.datetime) -> str:
    """ISO 8601 in UTC with a Z, as the HTTP routes give times."""
    return t.astimezone(dt.UTC).isoformat().replace("+00:00", "Z")


def calibration_of(active: Any) -> CalibrationInUse | None:
    """The record a message's corrected tilt comes from, with its status (None: no active
    record)."""
    return calibration_json(active)


def _num(v: float) -> float | None:
    return None if math.isnan(v) else float(v)


class HistoryRing:
    """The last `capacity` readings as rows of floats (about 130 bytes each), oldest overwritten
    first."""

    def __init__(self, capacity: int) -> None:
        self.capacity = max(16, capacity)
        self._rows = np.full((self.capacity, len(_COLS)), np.nan)
        self._n = 0  # rows ever written

    def append(self, row: list[float]) -> None:
        self._rows[self._n % self.capacity] = row
        self._n += 1

    def __len__(self) -> int:
        return min(self._n, self.capacity)

    def since(self, bench_s: float) -> NDArray[np.float64]:
        """Rows stamped at or after `bench_s`, oldest first."""
        n = len(self)
        if n == 0:
            return self._rows[:0]
        start = self._n - n
        idx = np.arange(start, self._n) % self.capacity
        rows = self._rows[idx]
        return rows[rows[:, _C["bench_s"]] >= bench_s]


def due(t: float, next_t: float, period: float, eps: float) -> float | None:
    """Decimation to a rate: the next due time if a message stamped `t` is due, else None."""
    if t + eps < next_t:
        return None
    return next_t + period if next_t + period > t else t + period


def history_objects(rows: NDArray[np.float64], rate_hz: float, eps: float) -> list[HistoryReading]:
    """Reading-shaped objects (no seq) of history rows, decimated to at most `rate_hz` (bench
    time)."""
    out: list[HistoryReading] = []
    next_t = -math.inf
    period = 1.0 / rate_hz
    for row in rows:
        nxt = due(row[_C["bench_s"]], next_t, period, eps)
        if nxt is None:
            continue
        next_t = nxt
        out.append(_row_object(row))
    return out


def _row_object(r: NDArray[np.float64]) -> HistoryReading:
    def c(name: str) -> float | None:
        return _num(r[_C[name]])

    def pair(a: str, b: str) -> SensorTilt | None:
        return None if math.isnan(r[_C[a]]) else {"x_deg": c(a), "y_deg": c(b)}

    return {
        "time_utc": utc_text(dt.datetime.fromtimestamp(r[_C["epoch"]], dt.UTC)),
        "type": "reading",
        "raw": {"measurement_sensor": pair("mx", "my"), "reference_sensor": pair("rx", "ry")},
        "table_tilt": None
        if math.isnan(r[_C["table"]])
        else from_expanded(
            {"x_deg": c("tx"), "y_deg": c("ty")},
            {"x": c("ux"), "y": c("uy")},
            {"x": c("kx"), "y": c("ky")},
            c("coverage"),
        ),
        "reference_tilt": None
        if math.isnan(r[_C["rtx"]])
        else {"x_deg": c("rtx"), "y_deg": c("rty")},
        "in_calibrated_range": None if math.isnan(r[_C["in_range"]]) else bool(r[_C["in_range"]]),
        "stage": None
        if math.isnan(r[_C["stage"]])
        else {"x_deg": c("sx"), "y_deg": c("sy"), "moving": bool(r[_C["moving"]])},
        "temp_c": c("temp"),
    }


@dataclass(frozen=True, eq=False)
class SnapshotBuild:
    """A snapshot's parts copied at connection time: its head (the newest reading, the calibration)
    and its history rows. Building the message from them is pure work on copies: a thread may do
    it."""

    head: SnapshotHead
    rows: NDArray[np.float64]
    rate_hz: float
    eps: float

    @property
    def size(self) -> int:
        return len(self.rows)

    def document(self) -> SnapshotMessage:
        return {**self.head, "history": history_objects(self.rows, self.rate_hz, self.eps)}

    def __call__(self) -> str:
        return json.dumps(self.document())


class SnapshotsBusy(RuntimeError):
    """As many snapshots as the daemon builds at once are being built, and as many wait as may."""


class SnapshotGate:
    """Snapshots with a long history are built `builds` at a time (in threads), `waiting` more may
    wait for their turn; one more is refused (SnapshotsBusy). Short ones (`small_rows` rows or
    fewer) pass at once."""

    def __init__(self, builds: int = 2, waiting: int = 8, small_rows: int = 1000) -> None:
        self.builds, self.waiting_max, self.small_rows = builds, waiting, small_rows
        self._slots = asyncio.Semaphore(builds)
        self.waiting = 0
        self.refused = 0

    async def build(self, snapshot: SnapshotBuild) -> str:
        if snapshot.size <= self.small_rows:
            return await asyncio.to_thread(snapshot)
        if self.waiting >= self.waiting_max + self.builds:
            self.refused += 1
            raise SnapshotsBusy(
                f"{self.builds} snapshots with long histories are being built and "
                f"{self.waiting_max}"
                " wait (TILTLAB_MAX_SNAPSHOTS, TILTLAB_SNAPSHOT_QUEUE); try again in a few seconds"
            )
        self.waiting += 1
        try:
            async with self._slots:
                return await asyncio.to_thread(snapshot)
        finally:
            self.waiting -= 1


@dataclass(eq=False)
class Client:
    """One connected reader: its queue, its rate and its sequence numbers."""

    rate_hz: float
    queue: asyncio.Queue[str]
    seq: int = 0  # the last sequence number given (sent or dropped)
    next_bench_s: float = -math.inf  # when its next message is due (bench time)
    pending_drops: int = 0  # dropped since the last `dropped` message
    dropped_total: int = 0
    dropping_since: float | None = None  # real time of the first drop of the current run
    close_code: int | None = None
    close_reason: str = ""
    kicked: asyncio.Event = field(default_factory=asyncio.Event)
    # a snapshot still to build (deferred), sent before the queue
    snapshot: SnapshotBuild | None = None

    def kick(self, code: int, reason: str) -> None:
        if self.close_code is None:
            self.close_code, self.close_reason = code, reason
        self.kicked.set()


class ReadingProducer:
    """The one producer of a bench's reading stream."""

    def __init__(
        self, bench: BenchRuntime, active_of: Any, *, queue_size: int, slow_close_s: float
    ) -> None:
        self.bench = bench
        self._active_of = active_of  # () -> the bench's ActiveModel or None
        self.queue_size = queue_size
        self.slow_close_s = slow_close_s
        self.role = next(
            (role for role in ("measurement_sensor", *SENSOR_ROLES) if role in bench.devices), None
        )
        self.interval_s = bench.output_interval_s(self.role) if self.role else 1.0
        self.sensor_rate_hz = 1.0 / self.interval_s
        self.history = HistoryRing(int(HISTORY_MAX_S * self.sensor_rate_hz * 1.05) + 16)
        self.clients: set[Client] = set()
        # messages dropped for slow clients since start (the daemon's metrics)
        self.dropped_total = 0
        self.messages = 0
        self._latest: ReadingMessage | None = None  # the last message built (without seq)
        self._task: asyncio.Task[None] | None = None

    # ------------------------------------------------------------ life

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(
            self._run(), name=f"readings {self.bench.name}"
        )

    async def stop(self) -> None:
        for client in list(self.clients):
            client.kick(CLOSE_GOING_AWAY, "daemon shutting down")
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    @property
    def latest_message(self) -> ReadingMessage | None:
        """The newest reading message built (without seq), the one the fleet publishes."""
        return self._latest

    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    # ------------------------------------------------------------ clients

    def clamp_rate(self, rate_hz: float | None) -> float:
        """A client's rate: at most the sensors' output rate (higher asks are clamped to it)."""
        return self.sensor_rate_hz if rate_hz is None else min(rate_hz, self.sensor_rate_hz)

    def connect(self, rate_hz: float, history_s: float, *, deferred: bool = False) -> Client:
        """Register a client; its queue holds the snapshot (seq 0) already. `deferred`: the snapshot
        is not built here (on the event loop) but by `client.snapshot()`, in a thread, from what was
        copied now (the history up to this moment, which the stream then continues without a
        gap)."""
        client = Client(rate_hz, asyncio.Queue(self.queue_size))
        if deferred:
            client.snapshot = self.snapshot_later(rate_hz, history_s)
        else:
            client.queue.put_nowait(json.dumps(self.snapshot(rate_hz, history_s)))
        self.clients.add(client)
        return client

    def disconnect(self, client: Client) -> None:
        self.clients.discard(client)

    def snapshot(self, rate_hz: float, history_s: float) -> SnapshotMessage:
        return self.snapshot_later(rate_hz, history_s).document()

    def snapshot_later(self, rate_hz: float, history_s: float) -> SnapshotBuild:
        """What a snapshot is made of, copied now (cheap); the message is built from it later,
        anywhere."""
        latest = self._latest or self._build(self.bench.clock.monotonic())[0]
        rows = self.history.since(self.bench.clock.monotonic() - history_s)
        head: SnapshotHead = {
            "type": "snapshot",
            "seq": 0,
            "time_utc": latest["time_utc"],
            "bench": self.bench.name,
            "rate_hz": rate_hz,
            "raw": latest["raw"],
            "table_tilt": latest["table_tilt"],
            "reference_tilt": latest.get("reference_tilt"),
            "stage": latest["stage"],
            "temp_c": latest["temp_c"],
            "calibration": calibration_of(self._active_of()),
            "in_calibrated_range": latest.get("in_calibrated_range"),
        }
        return SnapshotBuild(head, rows, rate_hz, 0.25 * self.interval_s)

    # ------------------------------------------------------------ producing

    async def _run(self) -> None:
        bench = self.bench
        last_seen: float | None = None  # bench time of the newest reading looked at
        last_emitted = -math.inf  # bench time of the newest reading a message was built from
        last_emit = bench.clock.monotonic()
        wake = max(bench.clock.real_seconds(self.interval_s / 2), MIN_WAKE_S)
        # Every reading that arrived since the last wake gets its message (a wake that comes late,
        # on a busy event loop, loses none). A bench sped up past one reading per
        # MIN_CORRECTION_GAP_S of real time has its readings thinned to one per that gap, as `GET
        # /tilt` corrects them; a bench at its own pace keeps them all, even the ones a busy reader
        # thread stamped close together.
        paced = bench.clock.real_seconds(self.interval_s) >= MIN_CORRECTION_GAP_S
        min_gap = 0.0 if paced else bench.clock.bench_seconds(MIN_CORRECTION_GAP_S) * 0.999
        while True:
            await asyncio.sleep(wake)
            try:
                now = bench.clock.monotonic()
                new = self._new_readings(last_seen)
                if new:
                    last_seen = new[-1].bench_s
                    for reading in new:
                        if reading.bench_s - last_emitted >= min_gap:
                            last_emitted, last_emit = reading.bench_s, now
                            self._emit(now, reading)
                # a silent sensor still gets one message per interval
                elif now - last_emit >= self.interval_s:
                    last_emit = now
                    self._emit(now, None)
            except Exception:  # noqa: BLE001 - one bad message must not end the stream
                log.exception("reading stream of %s: a message could not be built", bench.name)

    def _new_readings(self, last_seen: float | None) -> list[Reading]:
        """The stream's role's readings since `last_seen`, at most one second of them (what a
        stalled loop catches up on); the latest alone at the start."""
        if self.role is None:
            return []
        if last_seen is None:
            latest = self.bench.latest(self.role)
            return [] if latest is None else [latest]
        new = self.bench.readings_after(self.role, last_seen)
        return new[-max(1, int(self.sensor_rate_hz)) :]

    def _emit(self, now_bench_s: float, reading: Reading | None) -> None:
        msg, row = self._build(now_bench_s, reading)
        self._latest = msg
        self.history.append(row)
        self.messages += 1
        if not self.clients:
            return  # kept for snapshots and the fleet; serialised only for someone to read it
        body = json.dumps(msg)[1:]  # serialised once; each client's seq goes in front
        t = row[0]
        loop_now = asyncio.get_running_loop().time()
        eps = 0.25 * self.interval_s
        for client in list(self.clients):
            if client.rate_hz >= self.sensor_rate_hz:  # the full rate: every reading
                self._offer(client, body, loop_now)
                continue
            nxt = due(t, client.next_bench_s, 1.0 / client.rate_hz, eps)
            if nxt is not None:
                client.next_bench_s = nxt
                self._offer(client, body, loop_now)

    def _offer(self, c: Client, body: str, loop_now: float) -> None:
        client_queue = c.queue
        if c.pending_drops and client_queue.maxsize - client_queue.qsize() >= 2:
            c.seq += 1
            dropped: DroppedMessage = {"seq": c.seq, "type": "dropped", "count": c.pending_drops}
            client_queue.put_nowait(json.dumps(dropped))
            c.pending_drops = 0
        c.seq += 1
        if not c.pending_drops and not client_queue.full():
            client_queue.put_nowait(f'{{"seq":{c.seq},{body}')
            c.dropping_since = None
            return
        c.pending_drops += 1
        c.dropped_total += 1
        self.dropped_total += 1
        if c.dropping_since is None:
            c.dropping_since = loop_now
        elif loop_now - c.dropping_since >= self.slow_close_s:
            c.kick(CLOSE_SLOW, f"too slow: every message dropped for {self.slow_close_s:g} s")
            self.clients.discard(c)

    def _build(
        self, now_bench_s: float, reading: Reading | None = None
    ) -> tuple[ReadingMessage, list[float]]:
        """The message of `reading` (the stream role's; None: its latest) with the bench's other
        values now."""
        bench = self.bench
        clock = bench.clock
        # GET /tilt's rule
        limit = clock.bench_seconds(stale_after_s(bench, self.role)) if self.role else math.inf

        def fresh(role: str) -> Reading | None:
            found = reading if reading is not None and role == self.role else bench.latest(role)
            if (
                found is None
                or found.x_deg is None
                or found.y_deg is None
                or now_bench_s - found.bench_s > limit
            ):
                return None
            return found

        meas, ref = fresh("measurement_sensor"), fresh("reference_sensor")
        active = self._active_of()
        table = (
            corrected_once(bench, active, meas)
            if meas is not None and active is not None and bench.kind == "stage"
            else None
        )
        pose = bench.pose
        stage: StageTilt | None = (
            {"x_deg": pose.x_deg, "y_deg": pose.y_deg, "moving": pose.moving}
            if bench.kind == "stage"
            else None
        )
        temp = sensor_temp_c(meas, ref)
        when = meas.time_utc if meas is not None else clock.utc()
        t_bench = meas.bench_s if meas is not None else now_bench_s
        in_range = in_calibrated_range(active, table)
        through = reference_tilt(active, ref, temp) if bench.kind == "stage" else None
        msg: ReadingMessage = {
            "time_utc": utc_text(when),
            "type": "reading",
            "raw": {"measurement_sensor": _pair(meas), "reference_sensor": _pair(ref)},
            "reference_tilt": through,
            "table_tilt": table,
            "in_calibrated_range": in_range,
            "stage": stage,
            "temp_c": temp,
            "calibration": calibration_of(active),
        }  # an activation shows with the next reading
        row = _history_row(t_bench, when, meas, ref, table, stage, temp, in_range, through)
        return msg, row


def _pair(reading: Reading | None) -> SensorTilt | None:
    """A raw reading as a message shows it."""
    return None if reading is None else {"x_deg": reading.x_deg, "y_deg": reading.y_deg}


def _as_float(value: object) -> float:
    """A value for a history row, NaN where there is none."""
    if value is None:
        return math.nan
    if not isinstance(value, SupportsFloat):
        raise TypeError(f"a history row takes numbers, not {value!r}")
    return float(value)


def _of_reading(reading: Reading | None, name: str) -> float:
    """A reading's value for a history row (NaN without the reading)."""
    return _as_float(getattr(reading, name) if reading else None)


def _of_values(values: Mapping[str, object] | None, key: str) -> float:
    """An entry of a table tilt, stage pose or reference tilt for a history row (NaN without
    them)."""
    return _as_float(values[key] if values else None)


def _history_row(
    t_bench: float,
    when: dt.datetime,
    meas: Reading | None,
    ref: Reading | None,
    table: CorrectedTilt | None,
    stage: StageTilt | None,
    temp: float | None,
    in_range: bool | None,
    through: ReferenceTableTilt | None,
) -> list[float]:
    """A reading message's row of the history ring, in the order of its columns (_COLS)."""
    nan = math.nan
    return [
        t_bench,
        when.timestamp(),
        _of_reading(meas, "x_deg"),
        _of_reading(meas, "y_deg"),
        _of_reading(ref, "x_deg"),
        _of_reading(ref, "y_deg"),
        _of_values(table, "x_deg"),
        _of_values(table, "y_deg"),
        _of_values(table, "u_x_deg"),
        _of_values(table, "u_y_deg"),
        1.0 if table else nan,
        _of_values(stage, "x_deg"),
        _of_values(stage, "y_deg"),
        1.0 if stage and stage["moving"] else 0.0,
        1.0 if stage else nan,
        _as_float(temp),
        _of_values(table, "k"),
        _of_values(table, "k_y"),
        _of_values(table, "coverage_probability"),
        nan if in_range is None else float(in_range),
        _of_values(through, "x_deg"),
        _of_values(through, "y_deg"),
    ]


class StreamHub:
    """The producers of every bench, started and stopped with the daemon."""

    def __init__(
        self,
        benches: dict[str, BenchRuntime],
        jobs: Any,
        *,
        queue_size: int,
        slow_close_s: float,
        snapshots: SnapshotGate | None = None,
    ) -> None:
        self.snapshots = snapshots or SnapshotGate()
        self.producers = {
            name: ReadingProducer(
                bench,
                (lambda n=name: jobs.active.get(n)),
                queue_size=queue_size,
                slow_close_s=slow_close_s,
            )
            for name, bench in benches.items()
        }
        self.queue_size, self.slow_close_s = queue_size, slow_close_s
        self.remote: Any = None  # the fleet, when the daemon is part of one: other nodes' benches

    def start(self) -> None:
        for producer in self.producers.values():
            producer.start()

    async def stop(self) -> None:
        for producer in self.producers.values():
            await producer.stop()

    def find(self, name: str) -> ReadingProducer | None:
        """The stream of a bench of this daemon or, in a fleet, of another node's bench."""
        if name in self.producers:
            return self.producers[name]
        if self.remote is not None:
            producer: ReadingProducer | None = self.remote.producer(
                name, queue_size=self.queue_size, slow_close_s=self.slow_close_s
            )
            return producer
        return None

    def client_count(self) -> int:
        return sum(len(producer.clients) for producer in self.producers.values())
