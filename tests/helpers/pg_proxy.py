"""A TCP proxy between a daemon and PostgreSQL that a test cuts and restores, as a network or a
server restart would: cut, every connection is reset and new ones are refused; restored, it
forwards again on the same port. It can also lose the answer to one COMMIT (the server commits,
the client never hears it), the case that makes a repeated write dangerous. And it can hang: every
connection, open or new, is accepted and read but never answered (a server frozen, a firewall that
drops replies), which no TCP timeout of the client notices: the kernel acknowledges everything."""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
import time

import sqlalchemy as sa


class PgProxy:
    def __init__(self, target_host: str, target_port: int) -> None:
        self.target = (target_host, target_port)
        self._listener: socket.socket | None = None
        self.port = 0
        self._lock = threading.Lock()
        self._pairs: list[tuple[socket.socket, socket.socket]] = []
        self.lose_next_commit_answer = False
        self.commit_answers_lost = 0
        # set: nothing is passed on either way, new connections are only read
        self.hung = threading.Event()

    def url_of(self, database_url: str) -> str:
        """`database_url` reached through this proxy."""
        return (
            sa.make_url(database_url)
            .set(host="127.0.0.1", port=self.port)
            .render_as_string(hide_password=False)
        )

    def start(self) -> None:
        listener = socket.socket()
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", self.port))
        listener.listen(64)
        self.port = listener.getsockname()[1]
        self._listener = listener
        threading.Thread(target=self._accept, args=(listener,), daemon=True).start()

    def cut(self) -> None:
        """New connections are refused and every open one is reset."""
        listener, self._listener = self._listener, None
        if listener is not None:
            with contextlib.suppress(OSError):
                # wakes the accepting thread (a close alone would not)
                listener.shutdown(socket.SHUT_RDWR)
            listener.close()
        with self._lock:
            pairs, self._pairs = self._pairs, []
        for pair in pairs:
            _reset(*pair)

    def restore(self) -> None:
        self.start()

    def hang(self) -> None:
        """From now on nothing is passed on: the client's bytes are read and dropped, no answer
        comes."""
        self.hung.set()

    def stop(self) -> None:
        self.cut()

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return  # cut
            if self.hung.is_set():
                threading.Thread(target=self._swallow, args=(client,), daemon=True).start()
                continue
            try:
                server = socket.create_connection(self.target, timeout=5)
            except OSError:
                _reset(client)
                continue
            server.settimeout(None)
            pair = (client, server)
            with self._lock:
                self._pairs.append(pair)
            muted = threading.Event()  # the server's answers are no longer passed on
            threading.Thread(
                target=self._pump, args=(client, server, pair, muted, True), daemon=True
            ).start()
            threading.Thread(
                target=self._pump, args=(server, client, pair, muted, False), daemon=True
            ).start()

    def _pump(
        self,
        src: socket.socket,
        dst: socket.socket,
        pair: tuple[socket.socket, socket.socket],
        muted: threading.Event,
        from_client: bool,
    ) -> None:
        try:
            while True:
                data = src.recv(65536)
                if not data:
                    break
                if from_client and self.lose_next_commit_answer and b"COMMIT\x00" in data:
                    self.lose_next_commit_answer = False
                    muted.set()
                    dst.sendall(data)  # the server gets the COMMIT and commits ...
                    time.sleep(0.3)
                    self.commit_answers_lost += 1
                    break  # ... and the client's connection is reset before it hears so
                if (not from_client and muted.is_set()) or self.hung.is_set():
                    continue
                dst.sendall(data)
        except OSError:
            pass
        with self._lock:
            if pair in self._pairs:
                self._pairs.remove(pair)
        _reset(*pair)

    def _swallow(self, client: socket.socket) -> None:
        """A connection made while hung: read and dropped until the client gives up."""
        with self._lock:
            self._pairs.append((client, client))
        try:
            while client.recv(65536):
                pass
        except OSError:
            pass


def _reset(*socks: socket.socket) -> None:
    for s in socks:
        with contextlib.suppress(OSError):
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        with contextlib.suppress(OSError):
            s.shutdown(socket.SHUT_RDWR)  # wakes the thread reading it
        with contextlib.suppress(OSError):
            s.close()
