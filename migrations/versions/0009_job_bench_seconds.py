"""Jobs keep the bench time they spent: moving, settling and reading, and their total.

Revision ID: 0009_bench_seconds
Revises: 0008_tamper_evident
Create Date: 2026-12-02

`calibration_jobs.bench_seconds` is a JSON object {"total", "moving", "settling", "reading"} in
bench seconds, written with the job's progress; NULL for jobs run before this revision (their bench
time was not counted).
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0009_bench_seconds"
down_revision: str | Sequence[str] | None = "0008_tamper_evident"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("calibration_jobs", sa.Column("bench_seconds", sa.JSON(), nullable=True))


def downgrade() -> None:
    op.drop_column("calibration_jobs", "bench_seconds")
