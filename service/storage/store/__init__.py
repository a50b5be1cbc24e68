"""The lab's records, one repository per aggregate over one database: every state-changing action is
one transaction plus its audit event.

Each write method checks its input, writes, appends the audit event (through the database's one
audit writer) and commits, or leaves nothing behind. `Store(engine)` builds every repository over
the same `Database`: `store.devices`, `store.jobs`, `store.points`, `store.records`,
`store.retention`, `store.audit`, `store.tokens`, `store.diagnoses` and the LIMS side
(`store.standards`, `store.approvals`, `store.certificates`, `store.orders`, `store.feed`,
`store.webhooks`). A caller that needs one of them takes that one.
"""

from __future__ import annotations

import sqlalchemy as sa

from service.storage.store.approvals import ApprovalsRepo
from service.storage.store.audit import AuditRepo
from service.storage.store.certificates import CertificatesRepo
from service.storage.store.database import Database
from service.storage.store.devices import DevicesRepo
from service.storage.store.diagnoses import DiagnosesRepo
from service.storage.store.hashing import (
    audit_content,
    point_content,
    points_sha256,
    record_content,
)
from service.storage.store.jobs import TERMINAL, TRANSITIONS, JobsRepo
from service.storage.store.orders import OrdersRepo
from service.storage.store.points import PointsRepo
from service.storage.store.records import RecordsRepo
from service.storage.store.retention import RetentionRepo
from service.storage.store.standards import StandardsRepo
from service.storage.store.tokens import TokensRepo
from service.storage.store.webhooks import FeedRepo, WebhooksRepo


class Store:
    """Every repository of one database, built over the same engine and audit writer."""

    def __init__(self, engine: sa.Engine) -> None:
        self.engine = engine
        self.db = Database(engine)
        self.devices = DevicesRepo(self.db)
        self.jobs = JobsRepo(self.db)
        self.points = PointsRepo(self.db)
        self.records = RecordsRepo(self.db)
        self.retention = RetentionRepo(self.db)
        self.audit = AuditRepo(self.db)
        self.tokens = TokensRepo(self.db)
        self.diagnoses = DiagnosesRepo(self.db)
        self.standards = StandardsRepo(self.db)
        self.approvals = ApprovalsRepo(self.db)
        self.certificates = CertificatesRepo(self.db)
        self.orders = OrdersRepo(self.db)
        self.feed = FeedRepo(self.db)
        self.webhooks = WebhooksRepo(self.db)


__all__ = [
    "TERMINAL",
    "TRANSITIONS",
    "ApprovalsRepo",
    "AuditRepo",
    "CertificatesRepo",
    "Database",
    "DevicesRepo",
    "DiagnosesRepo",
    "FeedRepo",
    "JobsRepo",
    "OrdersRepo",
    "PointsRepo",
    "RecordsRepo",
    "RetentionRepo",
    "StandardsRepo",
    "Store",
    "TokensRepo",
    "WebhooksRepo",
    "audit_content",
    "point_content",
    "points_sha256",
    "record_content",
]
