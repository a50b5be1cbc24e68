"""Live streams over WebSocket: a bench's readings (`/ws/readings`) and a calibration job (`/ws/jobs/{id}`).

The token comes in the `token` query parameter (scope read). A refused connection is accepted and
closed at once with a code and a reason naming what was wrong (browsers see no HTTP status):
1008 for a missing, unknown or scope-less token and for an unusable parameter; 1013 for a client
that could not take its messages; 1001 when the daemon stops; 1000 after a job's end.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import socket
from typing import Any, cast

from fastapi import APIRouter, Request, WebSocket
from pydantic_core import to_jsonable_python
from starlette.websockets import WebSocketDisconnect, WebSocketState

from service.api.auth import websocket_principal
from service.api.routers.calibrations import job_json
from service.storage.errors import UnknownEntity
from service.streams.jobs import job_messages
from service.streams.readings import HISTORY_DEFAULT_S, HISTORY_MAX_S, Client, StreamHub

router = APIRouter(tags=["streams"])

CLOSE_NORMAL = 1000
CLOSE_POLICY = 1008
SEND_BUFFER_BYTES = 32_768  # per reading client: kernel send buffer and transport buffer (see _bound_buffers)
CLOSE_TIMEOUT_S = 5.0  # a close frame that cannot be written in this long (a peer that reads nothing) is dropped


async def _refuse(ws: WebSocket, reason: str) -> None:
    await ws.accept()
    await ws.close(CLOSE_POLICY, reason[:120])


async def _authorised(ws: WebSocket) -> bool:
    if websocket_principal(ws, "read") is not None:
        return True
    token = ws.query_params.get("token")
    await _refuse(ws, "token: missing (give ?token=...)" if not token else
                  "token: unknown, revoked, or without the read scope")
    return False


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


def _bound_buffers(ws: WebSocket) -> None:
    """Bound what a reading client's connection buffers below our queue (kernel send buffer, transport
    buffer): left to autotuning, Linux grows a socket's send buffer to 4 MB, minutes of readings, before a
    client that reads nothing is even noticed. The server's transport is found behind the ASGI `send`
    callable; a server that hides it keeps its defaults."""
    stack: list[Any] = [getattr(ws, "_send", None)]
    seen: set[int] = set()
    while stack:
        f = stack.pop()
        if f is None or id(f) in seen:
            continue
        seen.add(id(f))
        transport = getattr(getattr(f, "__self__", None), "transport", None)
        if isinstance(transport, asyncio.WriteTransport):
            with contextlib.suppress(Exception):
                transport.set_write_buffer_limits(high=SEND_BUFFER_BYTES)
                sock = transport.get_extra_info("socket")
                if sock is not None:
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)
            return
        for cell in getattr(f, "__closure__", None) or ():
            with contextlib.suppress(ValueError):
                if callable(cell.cell_contents):
                    stack.append(cell.cell_contents)


async def _until_disconnect(ws: WebSocket) -> None:
    """Read (and ignore) what the client sends until it goes."""
    while True:
        msg = await ws.receive()
        if msg["type"] == "websocket.disconnect":
            return


async def _close(ws: WebSocket, code: int, reason: str) -> None:
    if ws.application_state == WebSocketState.CONNECTED and ws.client_state == WebSocketState.CONNECTED:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(ws.close(code, reason[:120]), CLOSE_TIMEOUT_S)


@router.websocket("/ws/readings")
async def readings(ws: WebSocket) -> None:
    """Snapshot (with history), then one reading per interval at `rate_hz`; see docs/api.md."""
    if not await _authorised(ws):
        return
    hub: StreamHub = ws.app.state.streams
    name = ws.query_params.get("bench")
    if name is None or name == "":
        if len(hub.producers) != 1:
            return await _refuse(ws, f"bench: the daemon runs {len(hub.producers)} benches"
                                     f" ({', '.join(hub.producers)}); name one")
        producer = next(iter(hub.producers.values()))
    else:
        found = hub.find(name)
        if found is None:
            return await _refuse(ws, f"bench: no bench named {name[:30]!r}; benches: {', '.join(hub.producers)}")
        producer = found
    try:
        rate = producer.clamp_rate(_number(ws, "rate_hz", None))
        history_s = _number(ws, "history_s", HISTORY_DEFAULT_S)
        assert history_s is not None
        if history_s > HISTORY_MAX_S:
            raise ValueError(f"history_s: {history_s:g} is above the maximum of {HISTORY_MAX_S:g} s")
    except ValueError as exc:
        return await _refuse(ws, str(exc))
    await ws.accept()
    _bound_buffers(ws)
    client = producer.connect(rate, history_s)
    try:
        await _serve_client(ws, client)
    finally:
        producer.disconnect(client)


async def _serve_client(ws: WebSocket, client: Client) -> None:
    async def send() -> None:
        while True:
            await ws.send_text(await client.queue.get())

    tasks = [asyncio.create_task(send()), asyncio.create_task(_until_disconnect(ws)),
             asyncio.create_task(client.kicked.wait())]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    if client.close_code is not None:
        await _close(ws, client.close_code, client.close_reason)


@router.websocket("/ws/jobs/{job_id}")
async def job_stream(ws: WebSocket, job_id: str) -> None:
    """Snapshot (job and points so far), then `job` and `point` messages, then `end` and close 1000."""
    if not await _authorised(ws):
        return
    if not job_id.isdigit():
        return await _refuse(ws, f"id: {job_id[:20]!r} is not a job id")
    store = ws.app.state.store
    jobs = ws.app.state.jobs
    as_request = cast(Request, ws)  # job_json reads only app.state, which a WebSocket has too

    def body(job: Any) -> dict:
        return to_jsonable_python(job_json(as_request, job))  # as the HTTP route serialises it

    try:
        await asyncio.to_thread(store.get_job, int(job_id))
    except UnknownEntity:
        return await _refuse(ws, f"id: no calibration job {job_id}")
    await ws.accept()
    waiter = asyncio.create_task(_until_disconnect(ws))
    stream = job_messages(store, jobs.events, int(job_id), body)
    seq = 0
    try:
        while True:
            nxt = asyncio.ensure_future(anext(stream))
            done, _ = await asyncio.wait({nxt, waiter}, return_when=asyncio.FIRST_COMPLETED)
            if nxt not in done:
                nxt.cancel()
                with contextlib.suppress(asyncio.CancelledError, StopAsyncIteration):
                    await nxt
                return  # the client went
            try:
                msg = nxt.result()
            except StopAsyncIteration:
                break
            await ws.send_text(json.dumps({"seq": seq, **msg}))
            seq += 1
        await _close(ws, CLOSE_NORMAL, "job ended")
    except WebSocketDisconnect:
        return
    finally:
        waiter.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await waiter
        await stream.aclose()
