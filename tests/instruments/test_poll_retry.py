"""A state or position poll whose answer is lost on the line is asked again: one lost answer is not
a lost device, three unanswered in a row are (as the instruments documentation says)."""

from __future__ import annotations

import asyncio

import pytest

from service.bench.runtime import polled
from service.instruments.drivers import IDLE_POLL_MISSES
from service.instruments.transport import DeviceTimeout


class _Line:
    """A device whose first `lost` answers are lost, then answers `value`."""

    def __init__(self, lost: int, value: str) -> None:
        self.lost, self.value, self.asked = lost, value, 0

    async def state(self) -> str:
        self.asked += 1
        if self.asked <= self.lost:
            raise DeviceTimeout("stage: no answer to 1TS? within 0.2 s")
        return self.value


@pytest.mark.parametrize("lost", range(IDLE_POLL_MISSES))
def test_a_poll_with_fewer_lost_answers_than_the_limit_is_answered(lost):
    line = _Line(lost, "moving")
    assert asyncio.run(polled(line.state)) == "moving"
    assert line.asked == lost + 1


def test_three_unanswered_polls_in_a_row_raise():
    line = _Line(IDLE_POLL_MISSES, "ready")
    with pytest.raises(DeviceTimeout):
        asyncio.run(polled(line.state))
    assert line.asked == IDLE_POLL_MISSES == 3
