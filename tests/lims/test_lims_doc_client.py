"""The client of docs/lims.md ("A working client") run as written against `tiltlab serve`: the
puller reads the feed with a stored cursor, fetches each issued certificate and resumes where it
stopped; the webhook receiver's `handle` verifies the daemon's signed deliveries and sees each event
once."""

from __future__ import annotations

import contextlib
import http.server
import io
import re
import threading
import time
from pathlib import Path

import httpx
import pytest

from service.lims import dcc
from service.storage.engine import make_engine
from service.storage.store import Store
from tests.helpers.lims import ORDER, PEOPLE, STANDARD, measured_record
from tests.helpers.running_service import running_service
from tests.helpers.waiting import eventually

DOC = Path(__file__).resolve().parents[2] / "docs" / "lims.md"
LAB_ENV = {
    "TILTLAB_LAB_NAME": "Inclination Lab GmbH",
    "TILTLAB_LAB_CITY": "Braunschweig",
    "TILTLAB_LAB_COUNTRY_CODE": "DE",
    "TILTLAB_WEBHOOK_RETRY_BASE_S": "0.1",
    "TILTLAB_WEBHOOK_RETRY_MAX_S": "0.3",
}


class _Stop(Exception):
    """Raised from time.sleep: the puller has read the feed to its end."""


def client_blocks() -> tuple[str, str]:
    """The two Python blocks of the "A working client" section: the puller, the webhook receiver."""
    section = DOC.read_text().split("## A working client", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 2, "docs/lims.md: the working client is a puller and a receiver"
    return blocks[0], blocks[1]


def pull(code: str, base: str, cwd: Path, monkeypatch) -> list[str]:  # type: ignore[no-untyped-def]
    """Run the puller as written until it first waits for new events; the lines it printed."""
    assert 'BASE, TOKEN = "http://127.0.0.1:8000"' in code
    code = code.replace('"http://127.0.0.1:8000"', repr(base))

    def stop(_s: float) -> None:
        raise _Stop

    monkeypatch.chdir(cwd)
    monkeypatch.setattr(time, "sleep", stop)
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(_Stop):
        exec(compile(code, str(DOC), "exec"), {"__name__": "lims_client"})
    monkeypatch.undo()
    return out.getvalue().splitlines()


class DocReceiver:
    """An HTTP endpoint on 127.0.0.1 whose requests go to the documented `handle` function."""

    def __init__(self, code: str) -> None:
        self.ns: dict = {"__name__": "lims_receiver"}
        self.printed = io.StringIO()
        with contextlib.redirect_stdout(self.printed):
            exec(compile(code, str(DOC), "exec"), self.ns)
        self.secret = ""
        self.statuses: list[int] = []
        rx = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                body = self.rfile.read(int(self.headers["content-length"]))
                try:
                    with contextlib.redirect_stdout(rx.printed):
                        status = rx.ns["handle"](body, dict(self.headers), rx.secret)
                except Exception:  # a bad signature: the documented handle raises
                    status = 400
                rx.statuses.append(status)
                self.send_response(status)
                self.end_headers()

            def log_message(self, *args) -> None:  # type: ignore[no-untyped-def]
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def received(rx: DocReceiver) -> list[str]:
    """The events the documented receiver printed (each once, after verifying the signature)."""
    return [
        line for line in rx.printed.getvalue().splitlines() if line.startswith("tiltlab event ")
    ]


def test_the_documented_client_pulls_and_receives(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    puller, receiver = client_blocks()
    rx = DocReceiver(receiver)
    data = tmp_path / "data"
    try:
        with running_service(data, **LAB_ENV) as base:
            store = Store(make_engine(f"sqlite:///{data / 'tiltlab.db'}"))
            tokens = {
                name: store.tokens.create_token(
                    name, scopes, actor="setup", person=PEOPLE.get(name)
                )[1]
                for name, scopes in (("alice", "admin"), ("bob", "admin"), ("lims", "operate"))
            }
            auth = {k: {"Authorization": f"Bearer {v}"} for k, v in tokens.items()}
            (tmp_path / "lims.token").write_text(tokens["lims"] + "\n")
            with httpx.Client(base_url=base, timeout=10) as api:
                hook = api.post(
                    "/webhooks", json={"url": rx.url, "events": ["*"]}, headers=auth["alice"]
                )
                assert hook.status_code == 201, hook.text
                rx.secret = hook.json()["secret"]
                assert (
                    api.post("/standards", json=STANDARD, headers=auth["alice"]).status_code == 201
                )
                r = api.post(
                    "/orders", json=ORDER, headers={**auth["lims"], "Idempotency-Key": "doc-1"}
                )
                assert r.status_code == 201, r.text

                first = pull(puller, base, tmp_path, monkeypatch)
                assert any(" order.created " in line for line in first), first

                record = measured_record(store, started_by="alice")
                assert (
                    api.post(
                        f"/records/{record.id}/approve",
                        json={"meaning": "approval"},
                        headers=auth["bob"],
                    ).status_code
                    == 200
                )
                issued = api.get(f"/records/{record.id}/certificate", headers=auth["bob"])
                assert issued.status_code == 200, issued.text

                second = pull(puller, base, tmp_path, monkeypatch)
                feed = api.get("/feed", params={"limit": 1000}, headers=auth["lims"]).json()[
                    "events"
                ]
                eventually(
                    lambda: len(received(rx)) >= len(feed),
                    timeout_s=30,
                    every_s=0.05,
                    what="every event of the feed received",
                )
    finally:
        rx.close()
    # the puller saw every event once, in the feed's order, resuming from its stored cursor
    assert [line.split()[0] for line in first + second] == [e["id"] for e in feed]
    assert {line.split()[1] for line in second} >= {
        "record.created",
        "record.approved",
        "certificate.issued",
    }
    number = next(e["data"]["number"] for e in feed if e["type"] == "certificate.issued")
    xml = (tmp_path / f"{number}.xml").read_bytes()
    assert xml == issued.content and dcc.certificate_errors(xml) == []
    # the receiver verified every delivery and printed each event once
    events = received(rx)
    assert len(events) == len(feed) and set(rx.statuses) == {204}
    assert sorted(line.split()[2] for line in events) == sorted(e["type"] for e in feed)
