"""The daemon: job progress and interruption, API tokens (hashes only), idempotency keys.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-23

Jobs keep their state machine of 0001; this adds what the daemon persists at every step
(points done and total, the phase, the moment of the last change, whether a restart
interrupted it). Per-point measurements stay in `settled_points` and raw readings in
`samples` (both of 0001).
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | Sequence[str] | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

Utc = sa.DateTime(timezone=True)
Sha = sa.String(length=64)


def upgrade() -> None:
    with op.batch_alter_table("calibration_jobs") as batch:
        batch.add_column(sa.Column("points_done", sa.Integer(), nullable=False, server_default="0"))
        batch.add_column(
            sa.Column("points_total", sa.Integer(), nullable=False, server_default="0")
        )
        batch.add_column(sa.Column("phase", sa.String(length=16), nullable=True))
        batch.add_column(
            sa.Column("interrupted", sa.Boolean(), nullable=False, server_default=sa.false())
        )
        batch.add_column(sa.Column("updated_at", Utc, nullable=True))
    op.create_index("ix_calibration_jobs_updated_at", "calibration_jobs", ["updated_at"])

    op.create_table(
        "api_tokens",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=100), nullable=False),
        sa.Column("token_sha256", Sha, nullable=False),
        sa.Column("scopes", sa.JSON(), nullable=False),
        sa.Column("created_at", Utc, nullable=False),
        sa.Column("created_by", sa.String(length=100), nullable=False),
        sa.Column("revoked_at", Utc, nullable=True),
        sa.PrimaryKeyConstraint("id", name="pk_api_tokens"),
        sa.UniqueConstraint("name", name="uq_api_tokens_name"),
        sa.UniqueConstraint("token_sha256", name="uq_api_tokens_token_sha256"),
    )

    op.create_table(
        "idempotency_keys",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("key", sa.String(length=200), nullable=False),
        sa.Column("route", sa.String(length=100), nullable=False),
        sa.Column("request_sha256", Sha, nullable=False),
        sa.Column("job_id", sa.Integer(), nullable=True),
        sa.Column("created_at", Utc, nullable=False),
        sa.ForeignKeyConstraint(
            ["job_id"], ["calibration_jobs.id"], name="fk_idempotency_keys_job_id"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_idempotency_keys"),
        sa.UniqueConstraint("route", "key", name="uq_idempotency_keys_route_key"),
    )


def downgrade() -> None:
    op.drop_table("idempotency_keys")
    op.drop_table("api_tokens")
    op.drop_index("ix_calibration_jobs_updated_at", table_name="calibration_jobs")
    with op.batch_alter_table("calibration_jobs") as batch:
        batch.drop_column("updated_at")
        batch.drop_column("interrupted")
        batch.drop_column("phase")
        batch.drop_column("points_total")
        batch.drop_column("points_done")
