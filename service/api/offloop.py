"""A request's database work, off the event loop and with a deadline.

Every blocking call a request makes to the database (the token check first of all) runs in a
small thread pool of its own, never on the event loop: a database that hangs (a server that
accepts and never answers, a table locked by another client) holds up those threads, never
`/health`, `/tilt` or the instruments' streams. A call that has not finished after
`TILTLAB_DB_REQUEST_TIMEOUT_S` is answered 503 naming the database (the thread is left to finish
on its own: a thread cannot be stopped); when every thread of the pool already waits on the
database, a new call is answered 503 at once instead of queueing behind them.

Routes written as plain functions (they read the database) are made into such calls by
`off_loop`; the application's pool is found through the request's context (`use_calls`), set by
the authentication middleware for every request.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextvars
import functools
import threading
from collections.abc import Awaitable, Callable
from typing import ParamSpec, TypeVar

from service.api.problems import ProblemError

P = ParamSpec("P")
T = TypeVar("T")

RETRY_AFTER_S = 5


class DatabaseSlow(ProblemError):
    """The database did not answer a request's call in time, or every request thread waits on it."""

    def __init__(self, detail: str) -> None:
        super().__init__(
            503, "Database not answering", detail, headers={"Retry-After": str(RETRY_AFTER_S)}
        )


class DatabaseCalls:
    """A pool of `threads` threads for requests' database calls, each given `timeout_s`."""

    def __init__(
        self,
        where: str,
        timeout_s: float = 10.0,
        threads: int = 8,
        on_timeout: Callable[[BaseException], None] | None = None,
    ) -> None:
        self.where = where  # the database URL without its password
        self.timeout_s = timeout_s
        self.threads = threads
        self._on_timeout = on_timeout  # tells the daemon's database state that it does not answer
        self._pool = concurrent.futures.ThreadPoolExecutor(
            max_workers=threads, thread_name_prefix="tiltlab-request-db"
        )
        self._lock = threading.Lock()
        # calls handed to the pool and not yet returned (abandoned ones included)
        self.in_flight = 0
        self.timeouts = 0

    def _done(self, _: object) -> None:
        with self._lock:
            self.in_flight -= 1

    async def run(self, call: Callable[P, T], /, *args: P.args, **kwargs: P.kwargs) -> T:
        """`call(*args, **kwargs)` in the pool; DatabaseSlow (503) after the deadline or when the
        pool is full."""
        with self._lock:
            if self.in_flight >= self.threads:
                raise DatabaseSlow(
                    f"the database {self.where} is not answering: all {self.threads} threads "
                    "that carry requests to it (TILTLAB_DB_REQUEST_THREADS) are still waiting "
                    "for it; ask again once it answers (GET /health says when)"
                )
            self.in_flight += 1
        context = contextvars.copy_context()
        try:
            future = self._pool.submit(context.run, functools.partial(call, *args, **kwargs))
        except BaseException:
            self._done(None)
            raise
        future.add_done_callback(self._done)
        try:
            return await asyncio.wait_for(
                asyncio.shield(asyncio.wrap_future(future)), self.timeout_s
            )
        except TimeoutError:
            self.timeouts += 1
            error = TimeoutError(f"no answer within {self.timeout_s:g} s")
            if self._on_timeout is not None:
                self._on_timeout(error)
            raise DatabaseSlow(
                f"the database {self.where} did not answer within {self.timeout_s:g} s"
                " (TILTLAB_DB_REQUEST_TIMEOUT_S), so this request could not be carried out (if it"
                " changes something, the change may still be made once the database answers); ask"
                " again once it answers (GET /health says when)"
            ) from None

    def shutdown(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)


_current: contextvars.ContextVar[DatabaseCalls | None] = contextvars.ContextVar(
    "tiltlab_request_calls", default=None
)
_fallback: DatabaseCalls | None = None


def use_calls(calls: DatabaseCalls | None) -> None:
    """The pool this request's calls go to (set for each request by the authentication
    middleware)."""
    _current.set(calls)


def current_calls() -> DatabaseCalls:
    """The request's pool; outside a daemon's request (an application without its lifespan) a
    default one."""
    global _fallback
    calls = _current.get()
    if calls is not None:
        return calls
    if _fallback is None:
        _fallback = DatabaseCalls("the database")
    return _fallback


async def in_thread(call: Callable[P, T], /, *args: P.args, **kwargs: P.kwargs) -> T:
    """A blocking database call of a request, off the event loop and with the request deadline."""
    return await current_calls().run(call, *args, **kwargs)


def off_loop(route: Callable[P, T]) -> Callable[P, Awaitable[T]]:
    """A route written as a plain function (it reads or writes the database), run by `in_thread`."""

    @functools.wraps(route)
    async def run(*args: P.args, **kwargs: P.kwargs) -> T:
        return await in_thread(route, *args, **kwargs)

    return run
