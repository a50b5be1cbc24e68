"""What the LIMS integration runs inside the daemon: the webhook dispatcher and the daily check of
reference standards coming due. Started and stopped by the application's lifespan."""

from __future__ import annotations

import asyncio
import datetime as dt
import logging

from service.config import Settings
from service.lims.webhooks import Dispatcher
from service.storage.store import Store

log = logging.getLogger("tiltlab.lims")
DUE_CHECK_INTERVAL_S = 3600.0


class LimsRuntime:
    def __init__(self, store: Store, settings: Settings) -> None:
        self.store, self.settings = store, settings
        self.dispatcher = Dispatcher(store.webhooks, settings)
        self._due_task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        self.dispatcher.start()
        self._due_task = asyncio.create_task(self._check_due(), name="standards-due-check")

    async def stop(self) -> None:
        if self._due_task is not None:
            self._due_task.cancel()
            try:
                await self._due_task
            except asyncio.CancelledError:
                pass
        await self.dispatcher.stop()

    async def _check_due(self) -> None:
        while True:
            try:
                sent = await asyncio.to_thread(
                    self.store.standards.notify_standards_due,
                    today=dt.datetime.now(dt.UTC).date(),
                    within_days=self.settings.standards_due_soon_days,
                )
                if sent:
                    self.dispatcher.nudge()
            except asyncio.CancelledError:
                raise
            except Exception:  # noqa: BLE001 - checked again at the next interval
                log.exception("reference standards due check failed")
            await asyncio.sleep(DUE_CHECK_INTERVAL_S)
