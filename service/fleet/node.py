"""One node of the fleet: its leases, its published readings, its view of the other nodes' benches.

Names on the broker:
* key-value bucket `tiltlab_bench_leases` (entries expire after `fleet_lease_s`): bench -> its owner
  node and state, renewed every third of the lease while the node lives. A bench without an entry
  belongs to no live node.
* key-value bucket `tiltlab_benches` (kept): bench -> the node that last owned it, its kind and
  roles, so the fleet view still lists a bench whose node died (as offline).
* stream `TILTLAB_READINGS`, subjects `tiltlab.readings.<bench>`: each node's readings, decimated to
  `fleet_rate_hz`, kept for a minute, each with the node's `fleet_seq`.
* subject `tiltlab.commands.<node>`: request/reply carrying a bench command to the bench's owner.

The broker may come and go: the nats client reconnects by itself, leases are renewed and the fleet
view refreshed on the next tick, and readings published while it is away are dropped and counted.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, TypedDict, cast

import nats
import numpy as np
from nats.aio.client import Client as NatsClient
from nats.aio.msg import Msg
from nats.errors import NoRespondersError
from nats.errors import TimeoutError as NatsTimeout
from nats.js.api import DiscardPolicy, KeyValueConfig, StorageType
from nats.js.errors import (
    BadRequestError,
    BucketNotFoundError,
    KeyNotFoundError,
    KeyWrongLastSequenceError,
    NoKeysError,
)
from nats.js.errors import Error as JetStreamError
from nats.js.kv import KeyValue

from service.bench.runtime import BenchRuntime
from service.config import Settings
from service.errors import InputError
from service.storage.engine import redacted
from service.streams.messages import PublishedReading, ReadingMessage, SnapshotHead
from service.streams.readings import Client, ReadingProducer, SnapshotBuild, due

log = logging.getLogger("tiltlab.fleet")

LEASES = "tiltlab_bench_leases"
BENCHES = "tiltlab_benches"
READINGS_STREAM = "TILTLAB_READINGS"
READINGS_KEEP_S = 60.0
CONNECT_TIMEOUT_S = 2.0


def readings_subject(bench: str) -> str:
    return f"tiltlab.readings.{bench}"


def commands_subject(node: str) -> str:
    return f"tiltlab.commands.{node}"


class BenchEntry(TypedDict, total=False):
    """A bench's entry in `tiltlab_benches`: the node that last owned it, its kind and roles (as
    read back: an entry written by another version may lack a key)."""

    node: str
    kind: str
    roles: list[str]
    description: str


class LeaseEntry(BenchEntry, total=False):
    """A bench's lease in `tiltlab_bench_leases`: its entry and the bench's state now."""

    state: str


class BenchListing(TypedDict):
    """Another node's bench as GET /benches lists it."""

    name: str
    kind: str
    roles: list[str]
    description: str
    state: str
    held_by: None
    simulated: None
    node: str
    online: bool


class ForwardedRequest(TypedDict):
    """A bench read or command carried to the bench's owner on `tiltlab.commands.<node>`: the HTTP
    request as the caller sent it, with the caller's own headers (token, Idempotency-Key)."""

    method: str
    path: str
    query: str  # the query string, without the `?`; "" for none
    body: str
    headers: dict[str, str]


class ForwardedAnswer(TypedDict):
    """The owner's answer to a `ForwardedRequest`: its HTTP status, the headers that describe its
    content (content-type, location), and the content as text."""

    status: int
    headers: dict[str, str]
    body: str


class FleetConflict(InputError):
    """A bench this node would start is owned by another live node (the daemon exits 2)."""


class FleetUnavailable(Exception):
    """A command for another node's bench cannot be carried: its node is offline or the broker away
    (503)."""


@dataclass
class RemoteBench:
    """Another node's bench as this node knows it: who owns it, whether that node lives, its last
    reading."""

    name: str
    node: str
    kind: str = ""
    roles: list[str] = field(default_factory=list)
    description: str = ""
    state: str = "offline"
    online: bool = False
    latest: PublishedReading | None = None  # the last reading message received
    received_at: float | None = None  # time.monotonic() when it came
    listeners: set[Callable[[PublishedReading], None]] = field(default_factory=set)

    def listing(self) -> BenchListing:
        return {
            "name": self.name,
            "kind": self.kind,
            "roles": self.roles,
            "description": self.description,
            "state": self.state if self.online else "offline",
            "held_by": None,
            "simulated": None,
            "node": self.node,
            "online": self.online,
        }


Handler = Callable[[ForwardedRequest], Awaitable[ForwardedAnswer]]


class Fleet:
    """This daemon's membership of the fleet (only made when `broker_url` is set)."""

    def __init__(
        self,
        settings: Settings,
        benches: dict[str, BenchRuntime],
        latest_message: Callable[[str], ReadingMessage | None],
        handler: Handler,
    ) -> None:
        assert settings.broker_url
        self.node = settings.node
        self.url = settings.broker_url
        self.lease_s = settings.fleet_lease_s
        self.period_s = 1.0 / settings.fleet_rate_hz
        self.command_timeout_s = settings.fleet_command_timeout_s
        self.local = benches
        self._latest_message = latest_message
        self._handler = handler
        self.remote: dict[str, RemoteBench] = {}
        self._producers: dict[str, RemoteProducer] = {}
        self.published = 0
        self.dropped = 0  # readings not published because the broker was away
        self._nc: NatsClient | None = None
        self._leases: KeyValue | None = None
        self._benches: KeyValue | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._ready = asyncio.Event()  # buckets, stream and subscriptions are set up

    # ------------------------------------------------------------ life cycle

    async def start(self) -> None:
        """Join: claim this node's benches (FleetConflict if a live node owns one), then serve.

        A broker that does not answer at start-up does not stop the daemon: its own benches are
        served and the node joins when the broker comes (claiming its benches then)."""
        try:
            await self._connect()
            await self._setup()
        except FleetConflict:
            await self.stop()
            raise
        except (TimeoutError, OSError, nats.errors.Error) as exc:
            log.warning(
                "fleet: the broker at %s does not answer (%s); serving this node's benches alone"
                " until it does",
                redacted(self.url),
                exc,
            )
        self._tasks.append(asyncio.create_task(self._keep(), name="fleet leases and view"))
        self._tasks.append(asyncio.create_task(self._publish(), name="fleet readings"))

    async def stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        self._tasks.clear()
        nc, self._nc = self._nc, None
        if nc is None:
            return
        if nc.is_connected and self._leases is not None:  # a clean stop frees the benches at once
            for name in self.local:
                with contextlib.suppress(Exception):
                    await self._leases.delete(name)
        with contextlib.suppress(Exception):
            await nc.drain()

    @property
    def connected(self) -> bool:
        return self._nc is not None and self._nc.is_connected and self._ready.is_set()

    async def _connect(self) -> None:
        async def disconnected() -> None:
            log.warning(
                "fleet: lost the broker at %s; serving this node's benches alone",
                redacted(self.url),
            )

        async def reconnected() -> None:
            log.warning("fleet: the broker at %s is back", redacted(self.url))

        self._nc = await nats.connect(
            self.url,
            name=f"tiltlab {self.node}",
            connect_timeout=CONNECT_TIMEOUT_S,
            allow_reconnect=True,
            max_reconnect_attempts=-1,
            reconnect_time_wait=1,
            disconnected_cb=disconnected,
            reconnected_cb=reconnected,
        )

    async def _setup(self) -> None:
        """Buckets, stream, claims and subscriptions; again after a broker that lost its storage
        came back."""
        nc = self._nc
        assert nc is not None
        js = nc.jetstream()
        self._leases = await self._bucket(
            js, KeyValueConfig(bucket=LEASES, ttl=self.lease_s, history=1)
        )
        self._benches = await self._bucket(js, KeyValueConfig(bucket=BENCHES, history=1))
        # already there (perhaps made by another version): keep it
        with contextlib.suppress(BadRequestError):
            await js.add_stream(
                name=READINGS_STREAM,
                subjects=[readings_subject("*")],
                max_age=READINGS_KEEP_S,
                max_msgs_per_subject=int(READINGS_KEEP_S * 100),
                storage=StorageType.MEMORY,
                discard=DiscardPolicy.OLD,
            )
        for name in self.local:
            await self._claim(name)
        if not self._ready.is_set():
            await nc.subscribe(readings_subject("*"), cb=self._on_reading)
            await nc.subscribe(commands_subject(self.node), cb=self._on_command)
            self._ready.set()
        await self._refresh_view()

    @staticmethod
    async def _bucket(js: Any, config: KeyValueConfig) -> KeyValue:
        try:
            kv: KeyValue = await js.key_value(config.bucket)
        except BucketNotFoundError:
            kv = await js.create_key_value(config=config)
        return kv

    # ------------------------------------------------------------ leases

    def _client(self) -> NatsClient:
        """The broker connection, where the caller has seen it connected."""
        if self._nc is None:
            raise FleetUnavailable(f"node {self.node}: not connected to the fleet's broker")
        return self._nc

    def _lease_bucket(self) -> KeyValue:
        """The leases' bucket, where the caller has seen the node set up."""
        if self._leases is None:
            raise FleetUnavailable(f"node {self.node}: the fleet's buckets are not set up")
        return self._leases

    def _lease(self, name: str) -> bytes:
        bench = self.local[name]
        lease: LeaseEntry = {
            "node": self.node,
            "state": bench.state(),
            "kind": bench.kind,
            "roles": bench.roles(),
            "description": bench.config.description,
        }
        return json.dumps(lease).encode()

    async def _claim(self, name: str) -> None:
        assert self._leases is not None and self._benches is not None
        try:
            entry = await self._leases.get(name)
        except KeyNotFoundError:
            entry = None
        owner = json.loads(entry.value)["node"] if entry is not None and entry.value else None
        if owner is not None and owner != self.node:
            raise FleetConflict(
                f"bench {name!r} is owned by node {owner!r}, which is online; bench names are "
                f"unique in a fleet: rename this node's bench or stop node {owner!r} first"
            )
        if entry is None:
            try:
                await self._leases.create(name, self._lease(name))
            # another node claimed it between our read and our write
            except KeyWrongLastSequenceError:
                return await self._claim(name)
        else:
            await self._leases.put(name, self._lease(name))
        static = json.loads(self._lease(name))
        static.pop("state")
        await self._benches.put(name, json.dumps(static).encode())

    async def _keep(self) -> None:
        """Renew the leases and refresh the fleet view every third of a lease, whatever the broker
        does."""
        while True:
            await asyncio.sleep(self.lease_s / 3)
            try:
                await self._renew()
            except FleetConflict as exc:
                log.error("fleet: %s", exc)
            # e.g. a broker that came back without its storage: set it up again
            except JetStreamError as exc:
                log.info("fleet: %s; setting up the buckets and the stream again", exc)
                await self._set_up_again()
            except Exception as exc:  # noqa: BLE001 - the broker's troubles never stop the node
                log.info("fleet: renewing leases failed: %s", exc)

    async def _renew(self) -> None:
        """One tick of `_keep`: connected (and set up) first if need be, then this node's leases
        renewed and the fleet view refreshed."""
        if self._nc is None:
            await self._connect()
        if not self._client().is_connected:
            self._mark_unreachable()
            return
        if not self._ready.is_set():
            await self._setup()
            return
        for name in self.local:
            await self._lease_bucket().put(name, self._lease(name))
        await self._refresh_view()

    async def _set_up_again(self) -> None:
        """The buckets and the stream set up again after the broker lost them; a failure is left
        for the next tick."""
        try:
            await self._setup()
        except FleetConflict as conflict:
            log.error("fleet: %s", conflict)
        except Exception as again:  # noqa: BLE001 - tried again on the next tick
            log.info("fleet: setting up again failed: %s", again)

    def _mark_unreachable(self) -> None:
        for bench in self.remote.values():
            bench.online = False

    async def _refresh_view(self) -> None:
        """Every bench of the fleet with its node, from the two buckets."""
        assert self._leases is not None and self._benches is not None
        try:
            names = await self._benches.keys()
        except NoKeysError:
            names = []
        for name in names:
            if name in self.local:
                continue
            try:
                static: BenchEntry = json.loads((await self._benches.get(name)).value or b"{}")
            except KeyNotFoundError:
                continue
            lease: LeaseEntry
            try:
                lease = json.loads((await self._leases.get(name)).value or b"{}")
            except KeyNotFoundError:
                lease = {}
            self.remote[name] = self._viewed(name, static, lease)

    def _viewed(self, name: str, static: BenchEntry, lease: LeaseEntry) -> RemoteBench:
        """Another node's bench as its entries in the two buckets describe it (offline without a
        lease)."""
        bench = self.remote.get(name) or RemoteBench(name, static.get("node", "?"))
        bench.node = lease.get("node") or static.get("node", bench.node)
        bench.kind, bench.roles = static.get("kind", ""), list(static.get("roles", []))
        bench.description = static.get("description", "")
        bench.online = bool(lease)
        bench.state = lease.get("state", "offline")
        return bench

    # ------------------------------------------------------------ the fleet view

    def benches(self) -> list[BenchListing]:
        """The other nodes' benches, as GET /benches lists them."""
        return [
            bench.listing() for bench in sorted(self.remote.values(), key=lambda bench: bench.name)
        ]

    def is_remote(self, name: str | None) -> bool:
        return name is not None and name not in self.local and name in self.remote

    def producer(self, name: str, *, queue_size: int, slow_close_s: float) -> RemoteProducer | None:
        """The reading stream of another node's bench (one per bench, made on first use); None if
        unknown."""
        if not self.is_remote(name):
            return None
        producer = self._producers.get(name)
        if producer is None:
            producer = self._producers[name] = RemoteProducer(
                self.remote[name],
                rate_hz=1.0 / self.period_s,
                queue_size=queue_size,
                slow_close_s=slow_close_s,
            )
        return producer

    # ------------------------------------------------------------ readings

    async def _publish(self) -> None:
        """Each local bench's newest reading message, at most `fleet_rate_hz` a second, with a fleet
        sequence number."""
        last: dict[str, int] = {}
        seq = 0
        while True:
            await asyncio.sleep(self.period_s)
            for name in self.local:
                msg = self._latest_message(name)
                if msg is None or last.get(name) == id(msg):
                    continue  # nothing new since the last publication
                last[name] = id(msg)
                if not self.connected:
                    self.dropped += 1
                    continue
                seq += 1
                payload: PublishedReading = {
                    **msg,
                    "bench": name,
                    "node": self.node,
                    "fleet_seq": seq,
                }
                try:
                    await self._client().publish(
                        readings_subject(name), json.dumps(payload).encode()
                    )
                    self.published += 1
                except Exception:  # noqa: BLE001 - a broker going away while publishing: counted, not fatal
                    self.dropped += 1

    async def _on_reading(self, msg: Msg) -> None:
        try:
            payload: PublishedReading = json.loads(msg.data)  # as another node's `_publish` sent it
            name = payload["bench"]
        except (ValueError, KeyError, TypeError):
            return
        if name in self.local:
            return
        bench = self.remote.get(name)
        if bench is None:
            bench = self.remote[name] = RemoteBench(
                name, payload.get("node", "?"), online=True, state="ready"
            )
        bench.latest, bench.received_at = payload, time.monotonic()
        for listener in list(bench.listeners):
            listener(payload)

    # ------------------------------------------------------------ commands

    async def _on_command(self, msg: Msg) -> None:
        try:
            request: ForwardedRequest = json.loads(msg.data)  # as another node's `forward` sent it
            answer = await self._handler(request)
        except Exception as exc:  # noqa: BLE001 - the caller gets a problem, never silence
            log.exception("fleet: a command from another node failed")
            answer = {
                "status": 500,
                "headers": {"content-type": "application/problem+json"},
                "body": json.dumps(
                    {
                        "title": "Command failed on the bench's node",
                        "status": 500,
                        "detail": f"node {self.node}: {type(exc).__name__}: {exc}",
                    }
                ),
            }
        await msg.respond(json.dumps(answer).encode())

    async def forward(
        self, bench_name: str, request: ForwardedRequest
    ) -> tuple[ForwardedAnswer, float]:
        """Carry a request for another node's bench to its owner; its answer and the round trip in
        seconds."""
        bench = self.remote[bench_name]
        if not self.connected:
            raise FleetUnavailable(
                f"bench {bench_name!r} belongs to node {bench.node!r}, and the fleet's broker is"
                " not reachable from this node"
            )
        if not bench.online:
            raise FleetUnavailable(
                f"bench {bench_name!r} belongs to node {bench.node!r}, which is offline"
            )
        start = time.monotonic()
        try:
            reply = await self._client().request(
                commands_subject(bench.node),
                json.dumps(request).encode(),
                timeout=self.command_timeout_s,
            )
        except NoRespondersError:
            bench.online = False
            raise FleetUnavailable(
                f"bench {bench_name!r} belongs to node {bench.node!r}, which is offline"
            ) from None
        except NatsTimeout:
            raise FleetUnavailable(
                f"node {bench.node!r} did not answer for bench {bench_name!r} within"
                f" {self.command_timeout_s:g} s"
            ) from None
        answer: ForwardedAnswer = json.loads(reply.data)  # as the owner's `_on_command` sent it
        return answer, time.monotonic() - start


class RemoteProducer(ReadingProducer):
    """Another node's bench as a reading stream of this node: the owner's published readings, fanned
    out to this node's clients with their own `seq` and the same queue, drop and close rules as a
    local bench's stream. Its rate is the fleet's publication rate."""

    def __init__(
        self, bench: RemoteBench, *, rate_hz: float, queue_size: int, slow_close_s: float
    ) -> None:
        # no BenchRuntime here: the readings come from the broker, not from instruments
        self.remote = bench
        self.queue_size = queue_size
        self.slow_close_s = slow_close_s
        self.sensor_rate_hz = rate_hz
        self.interval_s = 1.0 / rate_hz
        self.clients: set[Client] = set()
        self.dropped_total = 0
        self.messages = 0
        self._latest = None
        self._task = None

    def connect(self, rate_hz: float, history_s: float, *, deferred: bool = False) -> Client:
        client = super().connect(rate_hz, history_s, deferred=deferred)
        self.remote.listeners.add(self._on_reading)
        return client

    def disconnect(self, client: Client) -> None:
        super().disconnect(client)
        if not self.clients:
            self.remote.listeners.discard(self._on_reading)

    def snapshot_later(self, rate_hz: float, history_s: float) -> SnapshotBuild:
        """The newest reading the owner published; no history (the owner's dashboard has it)."""
        # no reading received yet: every value None
        latest: PublishedReading | dict[str, None] = self.remote.latest or {}
        head: SnapshotHead = {
            "type": "snapshot",
            "seq": 0,
            "time_utc": latest.get("time_utc"),
            "bench": self.remote.name,
            "node": self.remote.node,
            "rate_hz": rate_hz,
            "raw": latest.get("raw"),
            "table_tilt": latest.get("table_tilt"),
            "stage": latest.get("stage"),
            "temp_c": latest.get("temp_c"),
            "calibration": latest.get("calibration"),
        }
        return SnapshotBuild(head, np.empty((0, 0)), rate_hz, 0.0)

    def _on_reading(self, payload: PublishedReading) -> None:
        # the owner's reading message as its producer built it (the keys it had, in its order)
        msg = cast(
            ReadingMessage,
            {
                key: value
                for key, value in payload.items()
                if key not in ("bench", "node", "fleet_seq")
            },
        )
        self._latest = msg
        self.messages += 1
        body = json.dumps(msg)[1:]
        loop_now = asyncio.get_running_loop().time()
        for client in list(self.clients):
            if client.rate_hz >= self.sensor_rate_hz:
                self._offer(client, body, loop_now)
                continue
            nxt = due(loop_now, client.next_bench_s, 1.0 / client.rate_hz, 0.25 * self.interval_s)
            if nxt is not None:
                client.next_bench_s = nxt
                self._offer(client, body, loop_now)
