"""Orders name the item's manufacturer and model, which certificates state (the instrument may not
report them).

Revision ID: 0006_certs
Revises: 0005_diagnosis
Create Date: 2026-11-24
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006_certs"
down_revision: str | Sequence[str] | None = "0005_diagnosis"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("orders") as batch:
        batch.add_column(sa.Column("item_manufacturer", sa.String(length=100), nullable=True))
        batch.add_column(sa.Column("item_model", sa.String(length=100), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("orders") as batch:
        batch.drop_column("item_model")
        batch.drop_column("item_manufacturer")
