"""Reference standards state their uncertainty as numbers: expanded uncertainty (degrees) and
coverage factor.

Revision ID: 0004_certs
Revises: 0003
Create Date: 2026-11-24

The free-text `uncertainty` stays as a remark. Existing standards get the numbers where their text
reads as an angle's expanded uncertainty with its coverage factor ("0.001 deg (k = 2)",
"3.6 arcsec, k = 2"); elsewhere they stay empty, and a job naming such a standard is refused until
it is registered again with the numbers. The reading rule is frozen here as it was at this revision.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004_certs"
down_revision: str | Sequence[str] | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_UNITS_DEG = {
    "deg": 1.0, "degree": 1.0, "degrees": 1.0, "°": 1.0,
    "arcmin": 1.0 / 60.0, "′": 1.0 / 60.0, "'": 1.0 / 60.0,
    "arcsec": 1.0 / 3600.0, "″": 1.0 / 3600.0, '"': 1.0 / 3600.0, "arc sec": 1.0 / 3600.0, "as": 1.0 / 3600.0,
    "mrad": 180.0 / math.pi / 1e3, "µrad": 180.0 / math.pi / 1e6, "urad": 180.0 / math.pi / 1e6,
    "rad": 180.0 / math.pi,
}  # fmt: skip
_UNIT = "|".join(sorted((re.escape(u) for u in _UNITS_DEG), key=len, reverse=True))
_TEXT = re.compile(
    rf"^\s*(?:U\s*=\s*)?(?:±|\+/-)?\s*(?P<value>\d+(?:\.\d*)?(?:[eE][-+]?\d+)?|\.\d+)\s*(?P<unit>{_UNIT})(?![A-Za-z])"
    r"\s*[,;(]?\s*k\s*=\s*(?P<k>\d+(?:\.\d*)?)\s*\)?\s*$"
)


def _parse(text: str | None) -> tuple[float, float] | None:
    m = _TEXT.match(text or "")
    if m is None:
        return None
    value, k = float(m["value"]), float(m["k"])
    if not (value > 0 and math.isfinite(value) and k >= 1 and math.isfinite(k)):
        return None
    return value * _UNITS_DEG[m["unit"]], k


def upgrade() -> None:
    with op.batch_alter_table("reference_standards") as batch:
        batch.add_column(sa.Column("expanded_uncertainty_deg", sa.Double(), nullable=True))
        batch.add_column(sa.Column("coverage_factor", sa.Double(), nullable=True))
    table = sa.table(
        "reference_standards",
        sa.column("id", sa.Integer()),
        sa.column("uncertainty", sa.Text()),
        sa.column("expanded_uncertainty_deg", sa.Double()),
        sa.column("coverage_factor", sa.Double()),
    )
    if (
        op.get_context().as_sql
    ):  # an offline SQL script is for a new database: no standards to read yet
        return
    bind = op.get_bind()
    for sid, text in bind.execute(sa.select(table.c.id, table.c.uncertainty)).all():
        parsed = _parse(text)
        if parsed is not None:
            bind.execute(
                table.update()
                .where(table.c.id == sid)
                .values(expanded_uncertainty_deg=parsed[0], coverage_factor=parsed[1])
            )


def downgrade() -> None:
    with op.batch_alter_table("reference_standards") as batch:
        batch.drop_column("coverage_factor")
        batch.drop_column("expanded_uncertainty_deg")
