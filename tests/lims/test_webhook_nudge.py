"""The webhook dispatcher is woken from the worker threads the routes run in, not only from its
event loop (an asyncio.Event set from another thread corrupts its waiters: a 500 on POST /webhooks,
found by the schemathesis test)."""

from __future__ import annotations

import asyncio
import threading

from service.config import Settings
from service.lims.webhooks import Dispatcher


class _NothingDue:
    def due_deliveries(self, now):
        return []

    def next_delivery_due(self):
        return None


def test_nudges_from_many_threads_wake_the_dispatcher_on_its_loop(tmp_path) -> None:
    async def main() -> list[bool]:
        dispatcher = Dispatcher(_NothingDue(), Settings(data_dir=tmp_path))  # type: ignore[arg-type]
        dispatcher.start()
        woken = []
        try:
            for _ in range(20):
                waiters = [asyncio.create_task(dispatcher.wake.wait()) for _ in range(5)]
                await asyncio.sleep(0)
                threads = [threading.Thread(target=dispatcher.nudge) for _ in range(8)]
                for thread in threads:
                    thread.start()
                for thread in threads:
                    await asyncio.to_thread(thread.join)
                done = await asyncio.wait_for(asyncio.gather(*waiters), timeout=30)
                woken.extend(done)
                dispatcher.wake.clear()
        finally:
            await dispatcher.stop()
        return woken

    woken = asyncio.run(main())
    assert woken == [True] * 100
