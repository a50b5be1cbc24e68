"""Diagnoses: the model-discrepancy workflow run on a stored record's points, and how each ended.

Revision ID: 0005_diagnosis
Revises: 0004_certs
Create Date: 2026-11-24

Both tables are append-only (guarded by triggers like the records of 0001): a diagnosis is asked
for once, and its result (the report and its page, or the reason it failed) is written once.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005_diagnosis"
down_revision: str | Sequence[str] | None = "0004_certs"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

Utc = sa.DateTime(timezone=True)
APPEND_ONLY = ("diagnoses", "diagnosis_results")


def upgrade() -> None:
    op.create_table(
        "diagnoses",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("record_id", sa.Integer(), nullable=False),
        sa.Column("sensor", sa.String(length=8), nullable=False),
        sa.Column("baseline", sa.String(length=20), nullable=False),
        sa.Column("created_by", sa.String(length=100), nullable=False),
        sa.Column("created_at", Utc, nullable=False),
        sa.ForeignKeyConstraint(
            ["record_id"], ["calibration_records.id"], name="fk_diagnoses_record_id"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_diagnoses"),
    )
    op.create_index("ix_diagnoses_record_id", "diagnoses", ["record_id"])
    op.create_table(
        "diagnosis_results",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("diagnosis_id", sa.Integer(), nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("started_at", Utc, nullable=True),
        sa.Column("finished_at", Utc, nullable=False),
        sa.Column("summary", sa.JSON(), nullable=False),
        sa.Column("report_html", sa.Text(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.CheckConstraint(
            sa.text("state IN ('succeeded', 'failed')"), name="ck_diagnosis_results_state"
        ),
        sa.ForeignKeyConstraint(
            ["diagnosis_id"], ["diagnoses.id"], name="fk_diagnosis_results_diagnosis_id"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_diagnosis_results"),
        sa.UniqueConstraint("diagnosis_id", name="uq_diagnosis_results_diagnosis_id"),
    )
    _create_guards()


def downgrade() -> None:
    _drop_guards()
    op.drop_table("diagnosis_results")
    op.drop_index("ix_diagnoses_record_id", table_name="diagnoses")
    op.drop_table("diagnoses")


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
