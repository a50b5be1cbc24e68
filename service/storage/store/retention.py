"""Retention of the monitoring samples, applied as one audited action."""

from __future__ import annotations

import datetime as dt

from service.storage import samples as samples_mod
from service.storage.store.base import StoreBase


class RetentionStore(StoreBase):
    def apply_retention(
        self,
        *,
        actor: str,
        older_than: dt.timedelta,
        policy: str = "thin",
        thin_interval_s: float = 60.0,
        now: dt.datetime | None = None,
    ) -> samples_mod.RetentionResult:
        with self._tx() as s:
            result = samples_mod.apply_retention(
                s.connection(), older_than=older_than, policy=policy, thin_interval_s=thin_interval_s, now=now
            )
            self._audit(
                s, actor, "retention.apply", "samples", "monitoring",
                {"policy": policy, "cutoff_s": result.cutoff_s, "deleted": result.deleted,
                 "thin_interval_s": thin_interval_s if policy == "thin" else None},
            )  # fmt: skip
            return result

    def apply_retention_from_settings(self, settings, *, actor: str = "retention") -> samples_mod.RetentionResult:  # type: ignore[no-untyped-def]
        return self.apply_retention(
            actor=actor,
            older_than=dt.timedelta(days=settings.monitoring_retention_days),
            policy=settings.monitoring_retention_policy,
            thin_interval_s=settings.monitoring_thin_interval_s,
        )
