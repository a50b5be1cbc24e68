"""LIMS integration: reference standards, orders, approvals, certificates, the event feed, webhooks.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-23

Approvals, certificates and feed events are append-only (guarded by triggers like the records
of 0001): an approval is a signature, a certificate is issued once, the feed never changes its
past. Webhook deliveries are the durable outbox (pending until delivered or given up); their
attempts are the delivery log.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | Sequence[str] | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

Utc = sa.DateTime(timezone=True)
Sha = sa.String(length=64)
BigId = sa.BigInteger().with_variant(sa.Integer(), "sqlite")
APPEND_ONLY = ("record_approvals", "certificates", "feed_events")


def upgrade() -> None:
    op.create_table(
        "orders",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("lims_order_id", sa.String(length=100), nullable=False),
        sa.Column("item_serial", sa.String(length=100), nullable=False),
        sa.Column("customer", sa.JSON(), nullable=False),
        sa.Column("procedure", sa.String(length=40), nullable=False),
        sa.Column("method", sa.String(length=80), nullable=False),
        sa.Column("due_on", sa.Date(), nullable=True),
        sa.Column("created_at", Utc, nullable=False),
        sa.Column("created_by", sa.String(length=100), nullable=False),
        sa.Column("idempotency_key", sa.String(length=200), nullable=True),
        sa.Column("request_sha256", Sha, nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_orders"),
        sa.UniqueConstraint("idempotency_key", name="uq_orders_idempotency_key"),
        sa.UniqueConstraint("lims_order_id", name="uq_orders_lims_order_id"),
    )
    op.create_table(
        "reference_standards",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=100), nullable=False),
        sa.Column("serial", sa.String(length=100), nullable=False),
        sa.Column("model", sa.String(length=100), nullable=True),
        sa.Column("certificate_number", sa.String(length=100), nullable=False),
        sa.Column("certificate_sha256", Sha, nullable=False),
        sa.Column("calibrated_on", sa.Date(), nullable=False),
        sa.Column("due_on", sa.Date(), nullable=False),
        sa.Column("uncertainty", sa.Text(), nullable=False),
        sa.Column("created_at", Utc, nullable=False),
        sa.Column("created_by", sa.String(length=100), nullable=False),
        sa.Column("due_soon_notified_on", sa.Date(), nullable=True),
        sa.PrimaryKeyConstraint("id", name="pk_reference_standards"),
        sa.UniqueConstraint(
            "serial", "certificate_number", name="uq_reference_standards_serial_certificate_number"
        ),
    )
    op.create_table(
        "webhook_endpoints",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("url", sa.Text(), nullable=False),
        sa.Column("events", sa.JSON(), nullable=False),
        sa.Column("secret", sa.String(length=100), nullable=False),
        sa.Column("created_at", Utc, nullable=False),
        sa.Column("created_by", sa.String(length=100), nullable=False),
        sa.Column("disabled_at", Utc, nullable=True),
        sa.PrimaryKeyConstraint("id", name="pk_webhook_endpoints"),
    )
    op.create_table(
        "feed_events",
        sa.Column("id", BigId, nullable=False),
        sa.Column("type", sa.String(length=40), nullable=False),
        sa.Column("at", Utc, nullable=False),
        sa.Column("data", sa.JSON(), nullable=False),
        sa.Column("audit_event_id", BigId, nullable=True),
        sa.PrimaryKeyConstraint("id", name="pk_feed_events"),
    )
    op.create_index("ix_feed_events_type", "feed_events", ["type"])
    op.create_table(
        "webhook_deliveries",
        sa.Column("id", BigId, nullable=False),
        sa.Column("endpoint_id", sa.Integer(), nullable=False),
        sa.Column("event_id", BigId, nullable=False),
        sa.Column("state", sa.String(length=12), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("next_attempt_at", Utc, nullable=True),
        sa.Column("last_status_code", sa.Integer(), nullable=True),
        sa.Column("last_error", sa.Text(), nullable=True),
        sa.Column("delivered_at", Utc, nullable=True),
        sa.Column("created_at", Utc, nullable=False),
        sa.CheckConstraint(
            "state IN ('pending', 'delivered', 'failed')", name="ck_webhook_deliveries_state"
        ),
        sa.ForeignKeyConstraint(
            ["endpoint_id"], ["webhook_endpoints.id"], name="fk_webhook_deliveries_endpoint_id"
        ),
        sa.ForeignKeyConstraint(
            ["event_id"], ["feed_events.id"], name="fk_webhook_deliveries_event_id"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_webhook_deliveries"),
        sa.UniqueConstraint(
            "endpoint_id", "event_id", name="uq_webhook_deliveries_endpoint_id_event_id"
        ),
    )
    op.create_index(
        "ix_webhook_deliveries_state_next_attempt_at",
        "webhook_deliveries",
        ["state", "next_attempt_at"],
    )
    op.create_table(
        "webhook_attempts",
        sa.Column("id", BigId, nullable=False),
        sa.Column("delivery_id", BigId, nullable=False),
        sa.Column("at", Utc, nullable=False),
        sa.Column("status_code", sa.Integer(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("duration_s", sa.Double(), nullable=False),
        sa.ForeignKeyConstraint(
            ["delivery_id"], ["webhook_deliveries.id"], name="fk_webhook_attempts_delivery_id"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_webhook_attempts"),
    )
    op.create_index("ix_webhook_attempts_delivery_id", "webhook_attempts", ["delivery_id"])
    op.create_table(
        "record_approvals",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("record_id", sa.Integer(), nullable=False),
        sa.Column("decision", sa.String(length=16), nullable=False),
        sa.Column("meaning", sa.String(length=40), nullable=False),
        sa.Column("note", sa.Text(), nullable=False),
        sa.Column("actor", sa.String(length=100), nullable=False),
        sa.Column("at", Utc, nullable=False),
        sa.Column("record_sha256", Sha, nullable=False),
        sa.Column("prev_sha256", Sha, nullable=False),
        sa.Column("sha256", Sha, nullable=False),
        sa.CheckConstraint(
            "decision IN ('approve', 'reject')", name="ck_record_approvals_decision"
        ),
        sa.ForeignKeyConstraint(
            ["record_id"], ["calibration_records.id"], name="fk_record_approvals_record_id"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_record_approvals"),
        sa.UniqueConstraint("prev_sha256", name="uq_record_approvals_prev_sha256"),
        sa.UniqueConstraint("sha256", name="uq_record_approvals_sha256"),
    )
    op.create_index("ix_record_approvals_record_id", "record_approvals", ["record_id"])
    op.create_table(
        "certificates",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("record_id", sa.Integer(), nullable=False),
        sa.Column("number", sa.String(length=100), nullable=False),
        sa.Column("xml", sa.LargeBinary(), nullable=False),
        sa.Column("sha256", Sha, nullable=False),
        sa.Column("approval_id", sa.Integer(), nullable=False),
        sa.Column("replaces_id", sa.Integer(), nullable=True),
        sa.Column("issued_at", Utc, nullable=False),
        sa.Column("issued_by", sa.String(length=100), nullable=False),
        sa.ForeignKeyConstraint(
            ["approval_id"], ["record_approvals.id"], name="fk_certificates_approval_id"
        ),
        sa.ForeignKeyConstraint(
            ["record_id"], ["calibration_records.id"], name="fk_certificates_record_id"
        ),
        sa.ForeignKeyConstraint(
            ["replaces_id"], ["certificates.id"], name="fk_certificates_replaces_id"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_certificates"),
        sa.UniqueConstraint("number", name="uq_certificates_number"),
        sa.UniqueConstraint("record_id", name="uq_certificates_record_id"),
    )
    with op.batch_alter_table("calibration_jobs") as batch:
        batch.add_column(sa.Column("order_id", sa.Integer(), nullable=True))
        batch.create_index("ix_calibration_jobs_order_id", ["order_id"], unique=False)
        batch.create_foreign_key("fk_calibration_jobs_order_id", "orders", ["order_id"], ["id"])
    _create_guards()


def downgrade() -> None:
    _drop_guards()
    with op.batch_alter_table("calibration_jobs") as batch:
        batch.drop_constraint("fk_calibration_jobs_order_id", type_="foreignkey")
        batch.drop_index("ix_calibration_jobs_order_id")
        batch.drop_column("order_id")
    op.drop_table("certificates")
    op.drop_index("ix_record_approvals_record_id", table_name="record_approvals")
    op.drop_table("record_approvals")
    op.drop_index("ix_webhook_attempts_delivery_id", table_name="webhook_attempts")
    op.drop_table("webhook_attempts")
    op.drop_index("ix_webhook_deliveries_state_next_attempt_at", table_name="webhook_deliveries")
    op.drop_table("webhook_deliveries")
    op.drop_index("ix_feed_events_type", table_name="feed_events")
    op.drop_table("feed_events")
    op.drop_table("webhook_endpoints")
    op.drop_table("reference_standards")
    op.drop_table("orders")


def _create_guards() -> None:
    """The same guards as 0001's append-only tables (PostgreSQL reuses 0001's trigger function)."""
    dialect = op.get_context().dialect.name
    for table in APPEND_ONLY:
        if dialect == "sqlite":
            for verb in ("UPDATE", "DELETE"):
                op.execute(
                    f"CREATE TRIGGER trg_{table}_no_{verb.lower()} BEFORE {verb} ON {table} "
                    f"BEGIN SELECT RAISE(ABORT, '{table} is append-only: {verb} refused'); END"
                )
        elif dialect == "postgresql":
            op.execute(
                f"CREATE TRIGGER trg_{table}_append_only BEFORE UPDATE OR DELETE ON {table} "
                "FOR EACH ROW EXECUTE FUNCTION tiltlab_refuse_change()"
            )
            op.execute(
                f"CREATE TRIGGER trg_{table}_no_truncate BEFORE TRUNCATE ON {table} "
                "FOR EACH STATEMENT EXECUTE FUNCTION tiltlab_refuse_change()"
            )
        else:
            raise NotImplementedError(f"append-only guards are not defined for {dialect}")


def _drop_guards() -> None:
    dialect = op.get_context().dialect.name
    for table in APPEND_ONLY:
        if dialect == "sqlite":
            op.execute(f"DROP TRIGGER IF EXISTS trg_{table}_no_update")
            op.execute(f"DROP TRIGGER IF EXISTS trg_{table}_no_delete")
        elif dialect == "postgresql":
            op.execute(f"DROP TRIGGER IF EXISTS trg_{table}_append_only ON {table}")
            op.execute(f"DROP TRIGGER IF EXISTS trg_{table}_no_truncate ON {table}")
