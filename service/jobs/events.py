"""Who wants to hear that a job changed: a subscriber list of asyncio events per job.

The job manager calls `changed(job_id)` after every state, progress or point it stores; a watcher
(the job stream) waits on its event and reads the job once per wake-up instead of polling the
database.
"""

from __future__ import annotations

import asyncio


class JobEvents:
    def __init__(self) -> None:
        self._watchers: dict[int, set[asyncio.Event]] = {}

    def subscribe(self, job_id: int) -> asyncio.Event:
        event = asyncio.Event()
        self._watchers.setdefault(job_id, set()).add(event)
        return event

    def unsubscribe(self, job_id: int, event: asyncio.Event) -> None:
        watchers = self._watchers.get(job_id)
        if watchers is not None:
            watchers.discard(event)
            if not watchers:
                del self._watchers[job_id]

    def changed(self, job_id: int) -> None:
        for event in self._watchers.get(job_id, ()):
            event.set()

    def watcher_count(self) -> int:
        return sum(len(watcher) for watcher in self._watchers.values())
