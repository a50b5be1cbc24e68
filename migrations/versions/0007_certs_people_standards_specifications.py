"""People behind tokens, who calibrated a reference standard, and what an order's item must meet.

Revision ID: 0007_certs_people
Revises: 0006_certs
Create Date: 2026-11-27

A token may name the person it belongs to (name and function); an approval keeps the signer's name
and function as they were when it was signed. A reference standard names the laboratory that
calibrated it. An order may carry a specification (largest permissible error and decision rule).
Every new column is empty for the rows already there: nothing is rewritten, so the append-only
approvals keep their hashes.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007_certs_people"
down_revision: str | Sequence[str] | None = "0006_certs"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # plain ADD COLUMN (no table copy): the append-only guard triggers of record_approvals stay in
    # place
    op.add_column("api_tokens", sa.Column("person_name", sa.String(length=200), nullable=True))
    op.add_column("api_tokens", sa.Column("person_function", sa.String(length=200), nullable=True))
    op.add_column(
        "record_approvals", sa.Column("signer_name", sa.String(length=200), nullable=True)
    )
    op.add_column(
        "record_approvals", sa.Column("signer_function", sa.String(length=200), nullable=True)
    )
    op.add_column("reference_standards", sa.Column("calibrated_by", sa.JSON(), nullable=True))
    op.add_column("orders", sa.Column("specification", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("orders") as batch:
        batch.drop_column("specification")
    with op.batch_alter_table("reference_standards") as batch:
        batch.drop_column("calibrated_by")
    with op.batch_alter_table("api_tokens") as batch:
        batch.drop_column("person_function")
        batch.drop_column("person_name")
    # record_approvals is append-only: on SQLite a batch copy would drop its guard triggers, so the
    # columns are dropped in place (SQLite 3.35 and later, PostgreSQL)
    op.drop_column("record_approvals", "signer_function")
    op.drop_column("record_approvals", "signer_name")
