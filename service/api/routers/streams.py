"""Live streams over WebSocket: a bench's readings (`/ws/readings`) and a calibration job
(`/ws/jobs/{id}`).

The token comes as the subprotocol `bearer.<token>` (echoed in the accept) or in the `token` query
parameter (scope read); it is asked again every few seconds, so a revoked token's streams end.
A refused connection is accepted and closed at once with a code and a reason naming what was wrong
(browsers see no HTTP status): 1008 for a missing, unknown, revoked or scope-less token and for an
unusable parameter; 1013 for a client that could not take its messages; 1001 when the daemon
stops; 1000 after a job's end.

A client that stops reading is found by the send itself, not by looking inside the server: each
message must be handed to the connection within the slow-close time, else the client is closed
(1013). What the connection buffers below the send is bounded where the daemon's listening socket
is made (service/api/limits.py: `bound_send_buffer`).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import re
from collections.abc import AsyncIterator

from fastapi import APIRouter, WebSocket
from starlette.websockets import WebSocketDisconnect, WebSocketState

from service.api.auth import websocket_principal, websocket_subprotocol
from service.api.deps import (
    BenchesDep,
    JobsDep,
    JobsRepoDep,
    PointsRepoDep,
    RecordsRepoDep,
    SettingsDep,
    StreamsDep,
)
from service.api.offloop import in_thread
from service.api.problems import ProblemError
from service.api.routers.calibrations import job_body
from service.io.json_value import JSONObject
from service.jobs.requests import DB_ID_MAX
from service.storage.errors import UnknownEntity
from service.storage.models import CalibrationJob
from service.streams.jobs import JobStreamMessage, job_messages
from service.streams.readings import (
    CLOSE_SLOW,
    HISTORY_DEFAULT_S,
    HISTORY_MAX_S,
    Client,
    ReadingProducer,
    SnapshotsBusy,
    StreamHub,
)

router = APIRouter(tags=["streams"])
log = logging.getLogger("tiltlab.streams")

CLOSE_NORMAL = 1000
CLOSE_POLICY = 1008
CLOSE_INTERNAL = 1011
# a close frame that cannot be written in this long (a peer that reads nothing) is dropped
CLOSE_TIMEOUT_S = 5.0
# an open stream asks for its token again this often (through the token cache)
TOKEN_RECHECK_S = 2.0
REVOKED = "token: revoked (or no longer valid)"


async def _accept(ws: WebSocket) -> None:
    """Accept, naming back the `bearer.<token>` subprotocol if the client offered it (browsers
    insist)."""
    await ws.accept(subprotocol=websocket_subprotocol(ws))


def _reason(text: str) -> str:
    """A close reason within the 123 bytes of UTF-8 a close frame has room for."""
    return text.encode("utf-8")[:120].decode("utf-8", errors="ignore")


async def _refuse(ws: WebSocket, reason: str) -> None:
    await _accept(ws)
    await ws.close(CLOSE_POLICY, _reason(reason))


async def _authorised(ws: WebSocket) -> bool:
    """The token checked before anything else (off the event loop when the database must be
    asked)."""
    try:
        await websocket_principal(ws, "read")
        return True
    except ProblemError as exc:
        given = websocket_subprotocol(ws) is not None or ws.query_params.get("token")
        if exc.status in (429, 503):  # try again later: the daemon could not check it now
            await _accept(ws)
            await ws.close(CLOSE_SLOW, _reason(f"token: {exc.detail}"))
        else:
            await _refuse(
                ws,
                "token: unknown, revoked, or without the read scope"
                if given
                else "token: missing (give the subprotocol bearer.<token>, or ?token=...)",
            )
        return False


async def _until_token_invalid(ws: WebSocket) -> None:
    """Return once the stream's token no longer lets it read (revoked here or by `tiltlab token
    revoke`).

    From the token cache: a known token is answered from memory and re-checked in the background."""
    while True:
        await asyncio.sleep(TOKEN_RECHECK_S)
        try:
            await websocket_principal(ws, "read")
        except ProblemError as exc:
            if exc.status in (401, 403):
                return
            log.warning(
                "a stream's token could not be checked (%s); asking again in %g s",
                exc.detail,
                TOKEN_RECHECK_S,
            )


def _number(ws: WebSocket, name: str, default: float | None) -> float | None:
    """A positive finite number from the query, or ValueError naming the parameter."""
    text = ws.query_params.get(name)
    if text is None or text == "":
        return default
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{name}: {text[:20]!r} is not a number") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name}: {text[:20]!r} must be a number > 0")
    return value


async def _until_disconnect(ws: WebSocket) -> None:
    """Read (and ignore) what the client sends until it goes."""
    while True:
        msg = await ws.receive()
        if msg["type"] == "websocket.disconnect":
            return


async def _close(ws: WebSocket, code: int, reason: str) -> None:
    if (
        ws.application_state == WebSocketState.CONNECTED
        and ws.client_state == WebSocketState.CONNECTED
    ):
        with contextlib.suppress(Exception):
            async with asyncio.timeout(CLOSE_TIMEOUT_S):
                await ws.close(code, _reason(reason))


async def _producer_asked(ws: WebSocket, hub: StreamHub) -> ReadingProducer | None:
    """The producer of the bench the query names (or of the only bench); None once a stream naming
    no bench of this daemon, or none of several, has been refused."""
    name = ws.query_params.get("bench")
    if name is None or name == "":
        if len(hub.producers) != 1:
            await _refuse(
                ws,
                f"bench: the daemon runs {len(hub.producers)} benches"
                f" ({', '.join(hub.producers)}); name one",
            )
            return None
        return next(iter(hub.producers.values()))
    found = hub.find(name)
    if found is None:
        await _refuse(
            ws, f"bench: no bench named {name[:30]!r}; benches: {', '.join(hub.producers)}"
        )
    return found


def _stream_asked(ws: WebSocket, producer: ReadingProducer) -> tuple[float, float]:
    """The rate (clamped to what the bench gives) and history the query asks for; ValueError
    naming the parameter that cannot be used."""
    rate = producer.clamp_rate(_number(ws, "rate_hz", None))
    history_s = _number(ws, "history_s", HISTORY_DEFAULT_S)
    assert history_s is not None
    if history_s > HISTORY_MAX_S:
        raise ValueError(f"history_s: {history_s:g} is above the maximum of {HISTORY_MAX_S:g} s")
    return rate, history_s


@router.websocket("/ws/readings")
async def readings(ws: WebSocket, hub: StreamsDep) -> None:
    """Snapshot (with history), then one reading per interval at `rate_hz`; see docs/api.md."""
    if not await _authorised(ws):
        return
    producer = await _producer_asked(ws, hub)
    if producer is None:
        return
    try:
        rate, history_s = _stream_asked(ws, producer)
    except ValueError as exc:
        return await _refuse(ws, str(exc))
    await _accept(ws)
    # the history copied now, the stream continues it
    client = producer.connect(rate, history_s, deferred=True)
    try:
        if client.snapshot is not None:  # built off the event loop, long histories a few at a time
            try:
                text = await hub.snapshots.build(client.snapshot)
            except SnapshotsBusy as exc:
                client.kick(CLOSE_SLOW, f"busy: {exc}")
                return await _close(ws, CLOSE_SLOW, client.close_reason)
            client.snapshot = None
            await ws.send_text(text)
        await _serve_client(ws, producer, client)
    finally:
        producer.disconnect(client)


async def _serve_client(ws: WebSocket, producer: ReadingProducer, client: Client) -> None:
    slow_close_s = producer.slow_close_s
    loop = asyncio.get_running_loop()
    # real time the send under way began (None: none under way)
    sending_since: list[float | None] = [None]
    queue = client.queue
    send_text = ws.send_text

    async def send() -> None:
        # Everything queued is sent in one wake; no timer per message (the watch below times the
        # sends).
        while True:
            text = await queue.get()
            while True:
                sending_since[0] = loop.time()
                await send_text(text)
                if queue.empty():
                    break
                text = queue.get_nowait()
            sending_since[0] = None

    async def watch() -> None:
        # A send that cannot be handed over: the client stopped reading and its buffers are full.
        step = min(0.5, slow_close_s / 10)
        while True:
            await asyncio.sleep(step)
            since = sending_since[0]
            if since is not None and loop.time() - since >= slow_close_s:
                client.kick(
                    CLOSE_SLOW, f"too slow: a message could not be sent for {slow_close_s:g} s"
                )
                return

    async def token() -> None:
        await _until_token_invalid(ws)
        client.kick(CLOSE_POLICY, REVOKED)

    tasks = [
        asyncio.create_task(send()),
        asyncio.create_task(_until_disconnect(ws)),
        asyncio.create_task(client.kicked.wait()),
        asyncio.create_task(token()),
        asyncio.create_task(watch()),
    ]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    # it gets nothing more, even while its close frame waits to be written
    producer.disconnect(client)
    for t in tasks:
        if not t.cancelled() and not isinstance(
            t.exception(), (type(None), WebSocketDisconnect, OSError)
        ):
            log.error("reading stream failed", exc_info=t.exception())
            client.kick(CLOSE_INTERNAL, "the stream failed; reconnect")
    if client.close_code is not None:
        await _close(ws, client.close_code, client.close_reason)


@router.websocket("/ws/jobs/{job_id}")
async def job_stream(
    ws: WebSocket,
    job_id: str,
    stored_jobs: JobsRepoDep,
    records: RecordsRepoDep,
    points: PointsRepoDep,
    jobs: JobsDep,
    benches: BenchesDep,
    settings: SettingsDep,
) -> None:
    """Snapshot (job and points so far), then `job` and `point` messages, then `end` and close
    1000."""
    if not await _authorised(ws):
        return
    if not re.fullmatch(r"[0-9]{1,10}", job_id) or not 1 <= int(job_id) <= DB_ID_MAX:
        return await _refuse(ws, f"id: {ascii(job_id[:20])} is not a job id")

    def body(job: CalibrationJob) -> JSONObject:
        record = records.records_of_jobs([job.id]).get(job.id)
        # as the HTTP route serialises it, and as the daemon knows it (an end not stored yet
        # included)
        return job_body(jobs.as_known(job), record, benches).model_dump(mode="json")

    try:
        await in_thread(stored_jobs.get_job, int(job_id))
    except UnknownEntity:
        return await _refuse(ws, f"id: no calibration job {job_id}")
    except ProblemError as exc:  # the database did not answer in time: try again later
        await _accept(ws)
        return await ws.close(CLOSE_SLOW, _reason(exc.detail))
    await _accept(ws)
    waiter = asyncio.create_task(_until_disconnect(ws))
    revoked = asyncio.create_task(_until_token_invalid(ws))
    stream = job_messages(stored_jobs, points, jobs.events, int(job_id), body)
    slow_close_s = settings.stream_slow_close_s
    try:
        await _send_job_messages(ws, stream, waiter, revoked, slow_close_s)
    except WebSocketDisconnect:
        return
    finally:
        for task in (waiter, revoked):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        await stream.aclose()


async def _send_job_messages(
    ws: WebSocket,
    stream: AsyncIterator[JobStreamMessage],
    waiter: asyncio.Task[None],
    revoked: asyncio.Task[None],
    slow_close_s: float,
) -> None:
    """The job's messages, numbered, until its end (close 1000), the client going, its token
    going (1008) or a message it does not take in time (1013)."""
    seq = 0
    while True:
        nxt = asyncio.ensure_future(anext(stream))
        done, _ = await asyncio.wait({nxt, waiter, revoked}, return_when=asyncio.FIRST_COMPLETED)
        if nxt not in done:
            nxt.cancel()
            with contextlib.suppress(asyncio.CancelledError, StopAsyncIteration):
                await nxt
            if revoked in done:
                await _close(ws, CLOSE_POLICY, REVOKED)
            return  # the client went, or its token did
        try:
            msg = nxt.result()
        except StopAsyncIteration:
            break
        try:
            async with asyncio.timeout(slow_close_s):
                await ws.send_text(json.dumps({"seq": seq, **msg}))
        except TimeoutError:
            await _close(
                ws, CLOSE_SLOW, f"too slow: a message could not be sent for {slow_close_s:g} s"
            )
            return
        seq += 1
    await _close(ws, CLOSE_NORMAL, "job ended")
