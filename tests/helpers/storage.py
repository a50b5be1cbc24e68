"""Shared constants and helpers of the storage tests."""

from __future__ import annotations

import sqlalchemy as sa


def count(engine: sa.Engine, table: str) -> int:
    with engine.connect() as conn:
        return int(conn.execute(sa.text(f"SELECT count(*) FROM {table}")).scalar_one())


STANDARDS = [{"name": "autocollimator", "serial": "AC-77", "certificate_id": "DAkkS-2025-0412"}]
MODEL = {
    "kind": "scale",
    "method": "linear",
    "parameters": {"gain_x": 1.0012, "gain_y": 0.9987},
    "covariance": [[1e-8, 0.0], [0.0, 1.1e-8]],
    "residuals": {"rms_deg": 0.0021},
}
