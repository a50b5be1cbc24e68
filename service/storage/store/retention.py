"""Retention of the monitoring samples, applied as one audited action."""

from __future__ import annotations

import datetime as dt
from typing import Protocol

from service.storage import samples as samples_mod
from service.storage.store.database import Database


class RetentionSettings(Protocol):
    """The settings that say how long monitoring samples are kept, and how they are thinned."""

    @property
    def monitoring_retention_days(self) -> float: ...
    @property
    def monitoring_retention_policy(self) -> str: ...
    @property
    def monitoring_thin_interval_s(self) -> float: ...


class RetentionRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def apply(
        self,
        *,
        actor: str,
        older_than: dt.timedelta,
        policy: str = "thin",
        thin_interval_s: float = 60.0,
        now: dt.datetime | None = None,
    ) -> samples_mod.RetentionResult:
        with self._db.transaction() as session:
            result = samples_mod.apply_retention(
                session.connection(),
                older_than=older_than,
                policy=policy,
                thin_interval_s=thin_interval_s,
                now=now,
            )
            self._db.audit(
                session,
                actor,
                "retention.apply",
                "samples",
                "monitoring",
                {
                    "policy": policy,
                    "cutoff_s": result.cutoff_s,
                    "deleted": result.deleted,
                    "thin_interval_s": thin_interval_s if policy == "thin" else None,
                },
            )
            return result

    def apply_from_settings(
        self, settings: RetentionSettings, *, actor: str = "retention"
    ) -> samples_mod.RetentionResult:
        return self.apply(
            actor=actor,
            older_than=dt.timedelta(days=settings.monitoring_retention_days),
            policy=settings.monitoring_retention_policy,
            thin_interval_s=settings.monitoring_thin_interval_s,
        )
