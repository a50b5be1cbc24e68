"""Initial schema: inventory, jobs, append-only calibration records, audit chain, samples.

Revision ID: 0001
Revises:
Create Date: 2026-11-22

The append-only guards are triggers, so that the database itself refuses UPDATE and DELETE
whatever client talks to it. Types here are plain SQLAlchemy types on purpose: a migration
is a frozen description and must not change when the models module does.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0001"
down_revision: str | Sequence[str] | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

APPEND_ONLY = (
    "calibration_records",
    "audit_events",
    "active_calibration_history",
    "settled_points",
)

BigId = sa.BigInteger().with_variant(sa.Integer(), "sqlite")
Utc = sa.DateTime(timezone=True)
Sha = sa.String(length=64)


def upgrade() -> None:
    op.create_table(
        "audit_events",
        sa.Column("id", BigId, nullable=False),
        sa.Column("at", Utc, nullable=False),
        sa.Column("actor", sa.String(length=100), nullable=False),
        sa.Column("action", sa.String(length=60), nullable=False),
        sa.Column("entity", sa.String(length=60), nullable=False),
        sa.Column("entity_id", sa.String(length=100), nullable=False),
        sa.Column("details", sa.JSON(), nullable=False),
        sa.Column("prev_sha256", Sha, nullable=False),
        sa.Column("sha256", Sha, nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_audit_events"),
        sa.UniqueConstraint("prev_sha256", name="uq_audit_events_prev_sha256"),
        sa.UniqueConstraint("sha256", name="uq_audit_events_sha256"),
    )
    op.create_index("ix_audit_events_at", "audit_events", ["at"])

    op.create_table(
        "benches",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=100), nullable=False),
        sa.Column("stage_model", sa.String(length=100), nullable=True),
        sa.Column("stage_serial", sa.String(length=100), nullable=True),
        sa.Column("port", sa.String(length=200), nullable=True),
        sa.Column("port_settings", sa.JSON(), nullable=False),
        sa.Column("created_at", Utc, nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_benches"),
        sa.UniqueConstraint("name", name="uq_benches_name"),
    )

    op.create_table(
        "devices",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("model", sa.String(length=100), nullable=False),
        sa.Column("serial", sa.String(length=100), nullable=False),
        sa.Column("role", sa.String(length=40), nullable=False),
        sa.Column("bench_id", sa.Integer(), nullable=True),
        sa.Column("port", sa.String(length=200), nullable=True),
        sa.Column("port_settings", sa.JSON(), nullable=False),
        sa.Column("created_at", Utc, nullable=False),
        sa.ForeignKeyConstraint(["bench_id"], ["benches.id"], name="fk_devices_bench_id"),
        sa.PrimaryKeyConstraint("id", name="pk_devices"),
        sa.UniqueConstraint("model", "serial", name="uq_devices_model_serial"),
    )

    op.create_table(
        "calibration_jobs",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("device_id", sa.Integer(), nullable=False),
        sa.Column("bench_id", sa.Integer(), nullable=True),
        sa.Column("kind", sa.String(length=40), nullable=False),
        sa.Column("method", sa.String(length=80), nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("progress", sa.Double(), nullable=False),
        sa.Column("parameters", sa.JSON(), nullable=False),
        sa.Column("failure_reason", sa.Text(), nullable=True),
        sa.Column("created_by", sa.String(length=100), nullable=False),
        sa.Column("created_at", Utc, nullable=False),
        sa.Column("started_at", Utc, nullable=True),
        sa.Column("finished_at", Utc, nullable=True),
        sa.CheckConstraint(
            "state IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')",
            name="ck_calibration_jobs_state",
        ),
        sa.CheckConstraint("progress >= 0 AND progress <= 1", name="ck_calibration_jobs_progress"),
        sa.ForeignKeyConstraint(["bench_id"], ["benches.id"], name="fk_calibration_jobs_bench_id"),
        sa.ForeignKeyConstraint(
            ["device_id"], ["devices.id"], name="fk_calibration_jobs_device_id"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_calibration_jobs"),
    )
    op.create_index("ix_calibration_jobs_device_id", "calibration_jobs", ["device_id"])

    op.create_table(
        "calibration_records",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("device_id", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(length=40), nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column("content_format", sa.SmallInteger(), nullable=False),
        sa.Column("method", sa.String(length=80), nullable=False),
        sa.Column("model", sa.JSON(), nullable=False),
        sa.Column("validation", sa.JSON(), nullable=False),
        sa.Column("temp_c", sa.Double(), nullable=True),
        sa.Column("reference_standards", sa.JSON(), nullable=False),
        sa.Column("operator", sa.String(length=100), nullable=False),
        sa.Column("created_at", Utc, nullable=False),
        sa.Column("job_id", sa.Integer(), nullable=True),
        sa.Column("raw_data", sa.JSON(), nullable=False),
        sa.Column("supersedes_id", sa.Integer(), nullable=True),
        sa.Column("prev_sha256", Sha, nullable=False),
        sa.Column("content_sha256", Sha, nullable=False),
        sa.CheckConstraint("version >= 1", name="ck_calibration_records_version"),
        sa.ForeignKeyConstraint(
            ["device_id"], ["devices.id"], name="fk_calibration_records_device_id"
        ),
        sa.ForeignKeyConstraint(
            ["job_id"], ["calibration_jobs.id"], name="fk_calibration_records_job_id"
        ),
        sa.ForeignKeyConstraint(
            ["supersedes_id"],
            ["calibration_records.id"],
            name="fk_calibration_records_supersedes_id",
        ),
        sa.PrimaryKeyConstraint("id", name="pk_calibration_records"),
        sa.UniqueConstraint("content_sha256", name="uq_calibration_records_content_sha256"),
        sa.UniqueConstraint(
            "device_id", "kind", "version", name="uq_calibration_records_device_id_kind_version"
        ),
        sa.UniqueConstraint(
            "id", "device_id", "kind", name="uq_calibration_records_id_device_id_kind"
        ),
    )
    op.create_index("ix_calibration_records_created_at", "calibration_records", ["created_at"])
    op.create_index("ix_calibration_records_job_id", "calibration_records", ["job_id"])

    op.create_table(
        "samples",
        sa.Column("id", BigId, nullable=False),
        sa.Column("device_id", sa.Integer(), nullable=False),
        sa.Column("t_s", sa.Double(), nullable=False),
        sa.Column("ch_x", sa.Double(), nullable=False),
        sa.Column("ch_y", sa.Double(), nullable=False),
        sa.Column("ch_z", sa.Double(), nullable=True),
        sa.Column("temp_c", sa.Double(), nullable=True),
        sa.Column("job_id", sa.Integer(), nullable=True),
        sa.Column("point", sa.Integer(), nullable=True),
        sa.Column("source", sa.String(length=12), nullable=False),
        sa.CheckConstraint(
            "source = 'monitoring' OR job_id IS NOT NULL", name="ck_samples_calibration_job"
        ),
        sa.CheckConstraint("source IN ('calibration', 'monitoring')", name="ck_samples_source"),
        sa.ForeignKeyConstraint(["device_id"], ["devices.id"], name="fk_samples_device_id"),
        sa.ForeignKeyConstraint(["job_id"], ["calibration_jobs.id"], name="fk_samples_job_id"),
        sa.PrimaryKeyConstraint("id", name="pk_samples"),
    )
    op.create_index("ix_samples_device_id_t_s", "samples", ["device_id", "t_s"])
    op.create_index(
        "ix_samples_job_id_point",
        "samples",
        ["job_id", "point"],
        sqlite_where=sa.text("job_id IS NOT NULL"),
        postgresql_where=sa.text("job_id IS NOT NULL"),
    )

    op.create_table(
        "settled_points",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("job_id", sa.Integer(), nullable=False),
        sa.Column("device_id", sa.Integer(), nullable=False),
        sa.Column("point", sa.Integer(), nullable=False),
        sa.Column("cmd_x_deg", sa.Double(), nullable=True),
        sa.Column("cmd_y_deg", sa.Double(), nullable=True),
        sa.Column("n_samples", sa.Integer(), nullable=False),
        sa.Column("t_start_s", sa.Double(), nullable=False),
        sa.Column("t_end_s", sa.Double(), nullable=False),
        sa.Column("ch_x_mean", sa.Double(), nullable=False),
        sa.Column("ch_y_mean", sa.Double(), nullable=False),
        sa.Column("ch_z_mean", sa.Double(), nullable=True),
        sa.Column("ch_x_std", sa.Double(), nullable=True),
        sa.Column("ch_y_std", sa.Double(), nullable=True),
        sa.Column("ch_z_std", sa.Double(), nullable=True),
        sa.Column("temp_c_mean", sa.Double(), nullable=True),
        sa.Column("created_at", Utc, nullable=False),
        sa.ForeignKeyConstraint(["device_id"], ["devices.id"], name="fk_settled_points_device_id"),
        sa.ForeignKeyConstraint(
            ["job_id"], ["calibration_jobs.id"], name="fk_settled_points_job_id"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_settled_points"),
        sa.UniqueConstraint(
            "job_id", "device_id", "point", name="uq_settled_points_job_id_device_id_point"
        ),
    )

    op.create_table(
        "active_calibration_history",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("device_id", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(length=40), nullable=False),
        sa.Column("record_id", sa.Integer(), nullable=True),
        sa.Column("previous_record_id", sa.Integer(), nullable=True),
        sa.Column("changed_at", Utc, nullable=False),
        sa.Column("changed_by", sa.String(length=100), nullable=False),
        sa.Column("reason", sa.Text(), nullable=False),
        sa.ForeignKeyConstraint(
            ["device_id"], ["devices.id"], name="fk_active_calibration_history_device_id"
        ),
        sa.ForeignKeyConstraint(
            ["previous_record_id"],
            ["calibration_records.id"],
            name="fk_active_calibration_history_previous_record_id",
        ),
        sa.ForeignKeyConstraint(
            ["record_id"],
            ["calibration_records.id"],
            name="fk_active_calibration_history_record_id",
        ),
        sa.PrimaryKeyConstraint("id", name="pk_active_calibration_history"),
    )
    op.create_index(
        "ix_active_calibration_history_device_id_kind_id",
        "active_calibration_history",
        ["device_id", "kind", "id"],
    )

    op.create_table(
        "active_calibrations",
        sa.Column("device_id", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(length=40), nullable=False),
        sa.Column("record_id", sa.Integer(), nullable=False),
        sa.Column("set_at", Utc, nullable=False),
        sa.Column("set_by", sa.String(length=100), nullable=False),
        sa.Column("reason", sa.Text(), nullable=False),
        sa.ForeignKeyConstraint(
            ["device_id"], ["devices.id"], name="fk_active_calibrations_device_id"
        ),
        sa.ForeignKeyConstraint(
            ["record_id", "device_id", "kind"],
            ["calibration_records.id", "calibration_records.device_id", "calibration_records.kind"],
            name="fk_active_calibrations_record_id_device_id_kind",
        ),
        sa.PrimaryKeyConstraint("device_id", "kind", name="pk_active_calibrations"),
    )

    _create_guards()


def downgrade() -> None:
    _drop_guards()
    op.drop_table("active_calibrations")
    op.drop_index(
        "ix_active_calibration_history_device_id_kind_id", table_name="active_calibration_history"
    )
    op.drop_table("active_calibration_history")
    op.drop_table("settled_points")
    op.drop_index("ix_samples_job_id_point", table_name="samples")
    op.drop_index("ix_samples_device_id_t_s", table_name="samples")
    op.drop_table("samples")
    op.drop_index("ix_calibration_records_job_id", table_name="calibration_records")
    op.drop_index("ix_calibration_records_created_at", table_name="calibration_records")
    op.drop_table("calibration_records")
    op.drop_index("ix_calibration_jobs_device_id", table_name="calibration_jobs")
    op.drop_table("calibration_jobs")
    op.drop_table("devices")
    op.drop_table("benches")
    op.drop_index("ix_audit_events_at", table_name="audit_events")
    op.drop_table("audit_events")


# Raw samples: never updated; only free-running monitoring samples may be deleted (retention).
_SQLITE_SAMPLES = (
    (
        "CREATE TRIGGER trg_samples_no_update BEFORE UPDATE ON samples "
        "BEGIN SELECT RAISE(ABORT, 'samples are raw data: UPDATE refused'); END"
    ),
    (
        "CREATE TRIGGER trg_samples_keep_calibration BEFORE DELETE ON samples WHEN OLD.source <> "
        "'monitoring' "
        "BEGIN SELECT RAISE(ABORT, 'samples of calibration jobs are kept: DELETE refused'); END"
    ),
)

_PG_FUNCTIONS = (
    """
    CREATE FUNCTION tiltlab_refuse_change() RETURNS trigger LANGUAGE plpgsql AS $$
    BEGIN
        RAISE EXCEPTION '% is append-only: % refused', TG_TABLE_NAME, TG_OP
            USING ERRCODE = 'restrict_violation';
    END
    $$
    """,
    """
    CREATE FUNCTION tiltlab_keep_calibration_samples() RETURNS trigger LANGUAGE plpgsql AS $$
    BEGIN
        IF TG_OP = 'UPDATE' THEN
            RAISE EXCEPTION 'samples are raw data: UPDATE refused' USING ERRCODE = 'restrict_violation';
        END IF;
        IF TG_OP = 'TRUNCATE' OR OLD.source <> 'monitoring' THEN
            RAISE EXCEPTION 'samples of calibration jobs are kept: % refused', TG_OP
                USING ERRCODE = 'restrict_violation';
        END IF;
        RETURN OLD;
    END
    $$
    """,
)


def _create_guards() -> None:
    dialect = op.get_context().dialect.name
    if dialect == "sqlite":
        for table in APPEND_ONLY:
            for verb in ("UPDATE", "DELETE"):
                op.execute(
                    f"CREATE TRIGGER trg_{table}_no_{verb.lower()} BEFORE {verb} ON {table} "
                    f"BEGIN SELECT RAISE(ABORT, '{table} is append-only: {verb} refused'); END"
                )
        for statement in _SQLITE_SAMPLES:
            op.execute(statement)
    elif dialect == "postgresql":
        for statement in _PG_FUNCTIONS:
            op.execute(statement)
        for table in APPEND_ONLY:
            op.execute(
                f"CREATE TRIGGER trg_{table}_append_only BEFORE UPDATE OR DELETE ON {table} "
                "FOR EACH ROW EXECUTE FUNCTION tiltlab_refuse_change()"
            )
            op.execute(
                f"CREATE TRIGGER trg_{table}_no_truncate BEFORE TRUNCATE ON {table} "
                "FOR EACH STATEMENT EXECUTE FUNCTION tiltlab_refuse_change()"
            )
        op.execute(
            "CREATE TRIGGER trg_samples_keep_calibration BEFORE UPDATE OR DELETE ON samples "
            "FOR EACH ROW EXECUTE FUNCTION tiltlab_keep_calibration_samples()"
        )
        op.execute(
            "CREATE TRIGGER trg_samples_no_truncate BEFORE TRUNCATE ON samples "
            "FOR EACH STATEMENT EXECUTE FUNCTION tiltlab_keep_calibration_samples()"
        )
    else:
        raise NotImplementedError(f"append-only guards are not defined for {dialect}")


def _drop_guards() -> None:
    dialect = op.get_context().dialect.name
    if dialect == "sqlite":
        for table in APPEND_ONLY:
            op.execute(f"DROP TRIGGER IF EXISTS trg_{table}_no_update")
            op.execute(f"DROP TRIGGER IF EXISTS trg_{table}_no_delete")
        op.execute("DROP TRIGGER IF EXISTS trg_samples_no_update")
        op.execute("DROP TRIGGER IF EXISTS trg_samples_keep_calibration")
    elif dialect == "postgresql":
        for table in (*APPEND_ONLY, "samples"):
            op.execute(f"DROP TRIGGER IF EXISTS trg_{table}_append_only ON {table}")
            op.execute(f"DROP TRIGGER IF EXISTS trg_{table}_no_truncate ON {table}")
        op.execute("DROP TRIGGER IF EXISTS trg_samples_keep_calibration ON samples")
        op.execute("DROP FUNCTION IF EXISTS tiltlab_keep_calibration_samples()")
        op.execute("DROP FUNCTION IF EXISTS tiltlab_refuse_change()")
