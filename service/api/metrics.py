"""Prometheus metrics of one daemon: its HTTP traffic, its instruments, its jobs and its streams.

HTTP requests are counted as they are answered, by route template (never the raw path, so an id
does not make a new series) and status, with a latency histogram. Everything else is read when
Prometheus scrapes, from where the daemon already keeps it: the drivers' frame counters, the jobs
table, the stream producers and the job writes in flight. Nothing is polled in between.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Annotated, Any, TypedDict

from fastapi import Depends, Request
from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector
from starlette.routing import Mount
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.bench.runtime import BenchRuntime
from service.storage.outage import DatabaseState
from service.streams.readings import StreamHub

# Latency buckets for a local service: /tilt answers in milliseconds, a job start in tens of them.
LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)

JOB_STATES = ("queued", "running", "succeeded", "failed", "cancelled", "interrupted")


class MetricSources(TypedDict, total=False):
    """The live objects a scrape reads, each absent until the daemon has it: the benches, the jobs
    per state (set by each scrape), the stream producers, the job writes in flight and the
    database's state."""

    benches: Mapping[str, BenchRuntime]
    job_counts: Callable[[], dict[str, int]]
    streams: StreamHub
    writes_in_flight: Callable[[], int]
    database: DatabaseState


class DaemonState(Collector):
    """Scrape-time readings of the daemon's own state; `sources` gives the live objects (or None
    before start-up)."""

    def __init__(self, sources: Callable[[], MetricSources]) -> None:
        self._sources = sources

    def collect(self) -> Iterator[GaugeMetricFamily | CounterMetricFamily]:
        src = self._sources()
        yield from _device_families(src.get("benches") or {})
        yield from _job_families(src.get("job_counts"))
        yield from _stream_families(src.get("streams"))
        in_flight = src.get("writes_in_flight")
        writes = GaugeMetricFamily(
            "tiltlab_sample_writer_queue_depth",
            "Job database writes (samples and settled points) handed over and not yet stored",
        )
        writes.add_metric([], float(in_flight() if callable(in_flight) else 0))
        yield writes
        yield from _database_families(src.get("database"))


def _database_families(database: Any) -> Iterable[GaugeMetricFamily]:
    up = GaugeMetricFamily(
        "tiltlab_database_up", "1 while the database answers, 0 while the daemon finds it away"
    )
    up.add_metric([], 0.0 if database is not None and not database.up else 1.0)
    yield up
    waiting = GaugeMetricFamily(
        "tiltlab_database_writes_waiting",
        "Job steps waiting for the database to answer again (their jobs paused)",
    )
    waiting.add_metric([], float(getattr(database, "writes_waiting", 0)))
    yield waiting
    samples = GaugeMetricFamily(
        "tiltlab_database_samples_waiting",
        "Raw samples held in memory by writes waiting for the database",
    )
    samples.add_metric([], float(getattr(database, "samples_waiting", 0)))
    yield samples


def _info_labels(key: list[str], st: Any) -> list[str]:
    """The labels of an instrument's `tiltlab_device_info`: where it is connected and what it said
    it is (empty before it said)."""
    ident = st.identity
    return [
        *key,
        str(st.port),
        str(st.protocol),
        ident.model if ident else "",
        (ident.serial or "") if ident else "",
        (ident.firmware or "") if ident else "",
    ]


def _device_families(
    benches: Mapping[str, BenchRuntime],
) -> Iterable[CounterMetricFamily | GaugeMetricFamily]:
    """Per instrument by bench and role, labels that stay the same when the daemon or a simulator
    restarts (a port can be a new pseudo-terminal each time); where it is connected and what it said
    it is are the labels of `tiltlab_device_info`, the usual Prometheus info metric (value 1),
    joined on bench and role."""
    labels = ["bench", "role"]
    families = {
        name: CounterMetricFamily(f"tiltlab_serial_{name}", help_text, labels=labels)
        for name, help_text in (
            ("frames", "Frames received from the instrument"),
            ("bad_checksums", "Frames refused for a bad checksum"),
            ("resyncs", "Times the framing lost and regained the frame boundary"),
            ("timeouts", "Requests the instrument did not answer in time"),
            ("reconnects", "Times the port was reopened"),
        )
    }
    connected = GaugeMetricFamily(
        "tiltlab_device_connected", "1 while the instrument answers, else 0", labels=labels
    )
    info = GaugeMetricFamily(
        "tiltlab_device_info",
        "Where each instrument is connected and what it reported itself to be (always 1)",
        labels=[*labels, "port", "protocol", "model", "serial", "firmware"],
    )
    for bench_name, bench in benches.items():
        for st in bench.devices.status():
            key = [bench_name, st.role]
            counters = st.counters
            for name, value in (
                ("frames", counters.frames),
                ("bad_checksums", counters.bad_checksum),
                ("resyncs", counters.resyncs),
                ("timeouts", counters.timeouts),
                ("reconnects", counters.reconnects),
            ):
                families[name].add_metric(key, float(value))
            connected.add_metric(key, 1.0 if st.state == "connected" else 0.0)
            info.add_metric(_info_labels(key, st), 1.0)
    yield from families.values()
    yield connected
    yield info


def _job_families(job_counts: Callable[[], dict[str, int]] | None) -> Iterable[GaugeMetricFamily]:
    jobs = GaugeMetricFamily(
        "tiltlab_jobs", "Calibration jobs in the database by state", labels=["state"]
    )
    counts = job_counts() if job_counts is not None else {}
    for state in sorted(set(JOB_STATES) | set(counts)):
        jobs.add_metric([state], float(counts.get(state, 0)))
    yield jobs


def _stream_families(hub: Any) -> Iterable[GaugeMetricFamily | CounterMetricFamily]:
    clients = GaugeMetricFamily(
        "tiltlab_websocket_clients", "Open reading streams", labels=["bench"]
    )
    dropped = CounterMetricFamily(
        "tiltlab_websocket_dropped_messages",
        "Reading messages dropped for clients that read too slowly",
        labels=["bench"],
    )
    for bench_name, producer in (getattr(hub, "producers", None) or {}).items():
        clients.add_metric([bench_name], float(len(producer.clients)))
        dropped.add_metric([bench_name], float(getattr(producer, "dropped_total", 0)))
    yield clients
    yield dropped


class Metrics:
    """One registry per application (tests run several daemons in one process)."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.requests = Counter(
            "tiltlab_http_requests",
            "HTTP requests answered",
            ["route", "method", "status"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "tiltlab_http_request_duration_seconds",
            "Time from request to the answer's start",
            ["route", "method"],
            buckets=LATENCY_BUCKETS_S,
            registry=self.registry,
        )
        self.sources: MetricSources = {}
        self.registry.register(DaemonState(lambda: self.sources))

    def observe(self, route: str, method: str, status: int, seconds: float) -> None:
        self.requests.labels(route, method, str(status)).inc()
        self.latency.labels(route, method).observe(seconds)


class MetricsMiddleware:
    """Counts every HTTP request by route template and status; WebSocket and lifespan pass
    through."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500  # what the client gets if the application raises before answering

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            self.metrics.observe(
                route_template(scope), scope["method"], status, time.perf_counter() - start
            )


def route_template(scope: Scope) -> str:
    """The route's template (an id makes no new series); a mounted folder's files as one template,
    `/web/{path}`."""
    route = scope.get("route")
    template = getattr(route, "path", None)
    if template:
        return str(template)
    for candidate in getattr(scope.get("app"), "routes", ()):
        if isinstance(candidate, Mount) and scope["path"].startswith(candidate.path + "/"):
            return f"{candidate.path}/{{path}}"
    return "(unmatched)"


def get_metrics(request: Request) -> Metrics:
    metrics: Metrics = request.app.state.metrics
    return metrics


MetricsDep = Annotated[Metrics, Depends(get_metrics)]
