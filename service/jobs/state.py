"""How a job ends when something other than its own work ends it: a cancel, a stop, the daemon
stopping."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from service.storage.models import JobState

__all__ = ["DAEMON", "Ending", "JobState", "Stop"]

DAEMON = "daemon"  # the actor of what the daemon does by itself


class Ending(StrEnum):
    CANCELLED = "cancelled"
    FAILED = "failed"
    # The daemon stopping: the job is left to be marked interrupted (resumable), not ended here.
    INTERRUPTED = "interrupted"


@dataclass(frozen=True)
class Stop:
    """Why a job's task was ended from outside, and who ended it (the audit's actor)."""

    ending: Ending
    reason: str
    actor: str = DAEMON
    # a failure the job may be resumed from (a full disk: its stored points are intact)
    resumable: bool = False

    @property
    def state(self) -> JobState:
        return JobState.CANCELLED if self.ending is Ending.CANCELLED else JobState.FAILED
