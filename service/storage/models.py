"""The database schema as typed SQLAlchemy models.

The migrations in `migrations/versions` must describe exactly this schema (a test compares them).
Tables named in APPEND_ONLY_TABLES are guarded by database triggers created in the migration:
no UPDATE or DELETE ever reaches them.
"""

from __future__ import annotations

import datetime as dt
from enum import StrEnum
from typing import Any

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column

from service.storage.errors import AppendOnlyViolation
from service.storage.specification import SpecificationJson

APPEND_ONLY_TABLES = (
    "calibration_records",
    "audit_events",
    "active_calibration_history",
    "settled_points",
    "record_approvals",
    "certificates",
    "feed_events",
    "diagnoses",
    "diagnosis_results",
)


class JobState(StrEnum):
    """A calibration job's state: queued -> running -> succeeded | failed | cancelled."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"


JOB_STATES = tuple(JobState)
SAMPLE_SOURCES = ("calibration", "monitoring")
GENESIS_SHA256 = "0" * 64

NAMING = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_N_name)s",
    "pk": "pk_%(table_name)s",
}


class UTCDateTime(sa.TypeDecorator[dt.datetime]):
    """Timezone-aware UTC on the way in and out, on every backend (SQLite keeps no zone)."""

    impl = sa.DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(
        self, value: dt.datetime | None, dialect: sa.Dialect
    ) -> dt.datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetime: storage takes timezone-aware UTC times only")
        value = value.astimezone(dt.UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(
        self, value: dt.datetime | None, dialect: sa.Dialect
    ) -> dt.datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=dt.UTC) if value.tzinfo is None else value.astimezone(dt.UTC)


# 64-bit keys where volume needs them; SQLite only aliases the rowid for exactly "INTEGER".
BigId = sa.BigInteger().with_variant(sa.Integer(), "sqlite")
Sha256 = sa.String(64)


def utc_now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


class Base(DeclarativeBase):
    metadata = sa.MetaData(naming_convention=NAMING)
    type_annotation_map = {
        dt.datetime: UTCDateTime(),
        float: sa.Double(),
        # JSON documents: those of one shape typed as such, the varied ones (a fitted model, a job's
        # parameters, an audit event's details...) as dict[str, Any]
        dict[str, Any]: sa.JSON(),
        dict[str, object]: sa.JSON(),
        dict[str, float]: sa.JSON(),
        dict[str, str]: sa.JSON(),
        list[Any]: sa.JSON(),
    }


class Bench(Base):
    __tablename__ = "benches"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(sa.String(100), unique=True)
    stage_model: Mapped[str | None] = mapped_column(sa.String(100))
    stage_serial: Mapped[str | None] = mapped_column(sa.String(100))
    port: Mapped[str | None] = mapped_column(sa.String(200))
    # the serial port's settings as the operator gave them (any JSON object)
    port_settings: Mapped[dict[str, object]] = mapped_column(default=dict)
    created_at: Mapped[dt.datetime] = mapped_column(default=utc_now)


class Device(Base):
    __tablename__ = "devices"
    __table_args__ = (sa.UniqueConstraint("model", "serial"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    model: Mapped[str] = mapped_column(sa.String(100))
    serial: Mapped[str] = mapped_column(sa.String(100))
    # e.g. "dut" (device under test), "reference", "stage-sensor".
    role: Mapped[str] = mapped_column(sa.String(40))
    bench_id: Mapped[int | None] = mapped_column(sa.ForeignKey("benches.id"))
    port: Mapped[str | None] = mapped_column(sa.String(200))
    # the serial port's settings as the operator gave them (any JSON object)
    port_settings: Mapped[dict[str, object]] = mapped_column(default=dict)
    created_at: Mapped[dt.datetime] = mapped_column(default=utc_now)


class CalibrationJob(Base):
    __tablename__ = "calibration_jobs"
    __table_args__ = (
        sa.CheckConstraint(
            sa.text("state IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')"),
            name="state",
        ),
        sa.CheckConstraint(sa.text("progress >= 0 AND progress <= 1"), name="progress"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    device_id: Mapped[int] = mapped_column(sa.ForeignKey("devices.id"), index=True)
    bench_id: Mapped[int | None] = mapped_column(sa.ForeignKey("benches.id"))
    kind: Mapped[str] = mapped_column(sa.String(40))
    method: Mapped[str] = mapped_column(sa.String(80))
    state: Mapped[str] = mapped_column(sa.String(16), default="queued")
    progress: Mapped[float] = mapped_column(sa.Double(), default=0.0)
    # The job's request and plan: their keys vary by procedure (service/jobs).
    parameters: Mapped[dict[str, Any]] = mapped_column(default=dict)
    failure_reason: Mapped[str | None] = mapped_column(sa.Text)
    created_by: Mapped[str] = mapped_column(sa.String(100))
    created_at: Mapped[dt.datetime] = mapped_column(default=utc_now)
    started_at: Mapped[dt.datetime | None]
    finished_at: Mapped[dt.datetime | None]
    # Persisted at every step by the daemon, so a restart knows where a job stood.
    points_done: Mapped[int] = mapped_column(default=0, server_default="0")
    points_total: Mapped[int] = mapped_column(default=0, server_default="0")
    phase: Mapped[str | None] = mapped_column(sa.String(16))
    # Set when a daemon restart found the job running: it is then failed and may be resumed.
    interrupted: Mapped[bool] = mapped_column(default=False, server_default=sa.false())
    updated_at: Mapped[dt.datetime | None] = mapped_column(
        index=True, default=utc_now, onupdate=utc_now
    )
    # The LIMS order the job works on, if any.
    order_id: Mapped[int | None] = mapped_column(sa.ForeignKey("orders.id"), index=True)
    # Bench time spent so far, by activity ({"total", "moving", "settling", "reading"}, bench
    # seconds).
    bench_seconds: Mapped[dict[str, float] | None]


class CalibrationRecord(Base):
    """One immutable calibration version of (device, kind); hashed and chained to its
    predecessor."""

    __tablename__ = "calibration_records"
    __table_args__ = (
        sa.UniqueConstraint("device_id", "kind", "version"),
        # Target of the active pointer's composite key: a pointer can only name a record of its own
        # device+kind.
        sa.UniqueConstraint("id", "device_id", "kind"),
        sa.CheckConstraint(sa.text("version >= 1"), name="version"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    device_id: Mapped[int] = mapped_column(sa.ForeignKey("devices.id"))
    kind: Mapped[str] = mapped_column(sa.String(40))
    version: Mapped[int]
    content_format: Mapped[int] = mapped_column(sa.SmallInteger, default=1)
    method: Mapped[str] = mapped_column(sa.String(80))
    # The fitted model document: parameters, covariance, residual statistics (varied: each method
    # has its own).
    model: Mapped[dict[str, Any]]
    # The validation's statistics, as the method that made the record states them (varied).
    validation: Mapped[dict[str, Any]] = mapped_column(default=dict)
    temp_c: Mapped[float | None] = mapped_column(sa.Double())
    # [{"name", "serial", "certificate_id"}] of the reference standards used.
    reference_standards: Mapped[list[Any]] = mapped_column(default=list)
    operator: Mapped[str] = mapped_column(sa.String(100))
    created_at: Mapped[dt.datetime] = mapped_column(index=True)
    job_id: Mapped[int | None] = mapped_column(sa.ForeignKey("calibration_jobs.id"), index=True)
    # Which raw data the fit came from (job points hash and counts, or an offline dataset's hash),
    # with the conditions, the uncertainty budget and what an adoption kept: varied by how the
    # record was made.
    raw_data: Mapped[dict[str, Any]] = mapped_column(default=dict)
    supersedes_id: Mapped[int | None] = mapped_column(sa.ForeignKey("calibration_records.id"))
    prev_sha256: Mapped[str] = mapped_column(Sha256)
    content_sha256: Mapped[str] = mapped_column(Sha256, unique=True)


class ActiveCalibration(Base):
    """The one active version per (device, kind): the primary key makes a second pointer
    impossible."""

    __tablename__ = "active_calibrations"
    __table_args__ = (
        sa.ForeignKeyConstraint(
            ["record_id", "device_id", "kind"],
            ["calibration_records.id", "calibration_records.device_id", "calibration_records.kind"],
        ),
    )

    device_id: Mapped[int] = mapped_column(sa.ForeignKey("devices.id"), primary_key=True)
    kind: Mapped[str] = mapped_column(sa.String(40), primary_key=True)
    record_id: Mapped[int]
    set_at: Mapped[dt.datetime]
    set_by: Mapped[str] = mapped_column(sa.String(100))
    reason: Mapped[str] = mapped_column(sa.Text)


class ActiveCalibrationHistory(Base):
    __tablename__ = "active_calibration_history"
    __table_args__ = (sa.Index(None, "device_id", "kind", "id"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    device_id: Mapped[int] = mapped_column(sa.ForeignKey("devices.id"))
    kind: Mapped[str] = mapped_column(sa.String(40))
    record_id: Mapped[int | None] = mapped_column(sa.ForeignKey("calibration_records.id"))
    previous_record_id: Mapped[int | None] = mapped_column(sa.ForeignKey("calibration_records.id"))
    changed_at: Mapped[dt.datetime]
    changed_by: Mapped[str] = mapped_column(sa.String(100))
    reason: Mapped[str] = mapped_column(sa.Text)


class AuditEvent(Base):
    """Who did what, when; one global hash chain (a unique predecessor makes forks impossible)."""

    __tablename__ = "audit_events"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    at: Mapped[dt.datetime] = mapped_column(index=True)
    actor: Mapped[str] = mapped_column(sa.String(100))
    action: Mapped[str] = mapped_column(sa.String(60))
    entity: Mapped[str] = mapped_column(sa.String(60))
    entity_id: Mapped[str] = mapped_column(sa.String(100))
    # What the action did: its keys vary by action.
    details: Mapped[dict[str, Any]] = mapped_column(default=dict)
    prev_sha256: Mapped[str] = mapped_column(Sha256, unique=True)
    sha256: Mapped[str] = mapped_column(Sha256, unique=True)


class Sample(Base):
    """One raw reading. High volume: written through `samples.insert_samples`, not the ORM."""

    __tablename__ = "samples"
    __table_args__ = (
        sa.CheckConstraint(sa.text("source IN ('calibration', 'monitoring')"), name="source"),
        sa.CheckConstraint(
            sa.text("source = 'monitoring' OR job_id IS NOT NULL"), name="calibration_job"
        ),
        sa.Index(None, "device_id", "t_s"),
        sa.Index(
            None,
            "job_id",
            "point",
            sqlite_where=sa.text("job_id IS NOT NULL"),
            postgresql_where=sa.text("job_id IS NOT NULL"),
        ),
    )

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    device_id: Mapped[int] = mapped_column(sa.ForeignKey("devices.id"))
    # Seconds since the Unix epoch, UTC.
    t_s: Mapped[float] = mapped_column(sa.Double())
    ch_x: Mapped[float] = mapped_column(sa.Double())
    ch_y: Mapped[float] = mapped_column(sa.Double())
    ch_z: Mapped[float | None] = mapped_column(sa.Double())
    temp_c: Mapped[float | None] = mapped_column(sa.Double())
    job_id: Mapped[int | None] = mapped_column(sa.ForeignKey("calibration_jobs.id"))
    point: Mapped[int | None]
    source: Mapped[str] = mapped_column(sa.String(12))


class SettledPoint(Base):
    """The settled average of one grid point of a job: what calibrations are fitted on."""

    __tablename__ = "settled_points"
    __table_args__ = (sa.UniqueConstraint("job_id", "device_id", "point"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    job_id: Mapped[int] = mapped_column(sa.ForeignKey("calibration_jobs.id"))
    device_id: Mapped[int] = mapped_column(sa.ForeignKey("devices.id"))
    point: Mapped[int]
    # Commanded stage tilt of the grid point, if the job has a stage.
    cmd_x_deg: Mapped[float | None] = mapped_column(sa.Double())
    cmd_y_deg: Mapped[float | None] = mapped_column(sa.Double())
    n_samples: Mapped[int]
    t_start_s: Mapped[float] = mapped_column(sa.Double())
    t_end_s: Mapped[float] = mapped_column(sa.Double())
    ch_x_mean: Mapped[float] = mapped_column(sa.Double())
    ch_y_mean: Mapped[float] = mapped_column(sa.Double())
    ch_z_mean: Mapped[float | None] = mapped_column(sa.Double())
    ch_x_std: Mapped[float | None] = mapped_column(sa.Double())
    ch_y_std: Mapped[float | None] = mapped_column(sa.Double())
    ch_z_std: Mapped[float | None] = mapped_column(sa.Double())
    temp_c_mean: Mapped[float | None] = mapped_column(sa.Double())
    created_at: Mapped[dt.datetime] = mapped_column(default=utc_now)
    # SHA-256 of the raw samples the point was averaged from (this job, device and point), part of
    # the point's hashed content and so of the record's: an edit of a raw sample breaks the chain
    samples_sha256: Mapped[str | None] = mapped_column(Sha256)


class ApiToken(Base):
    """A bearer token of the HTTP API: only its SHA-256 is kept; the token itself is shown once."""

    __tablename__ = "api_tokens"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(sa.String(100), unique=True)
    token_sha256: Mapped[str] = mapped_column(Sha256, unique=True)
    scopes: Mapped[list[Any]]
    created_at: Mapped[dt.datetime]
    created_by: Mapped[str] = mapped_column(sa.String(100))
    revoked_at: Mapped[dt.datetime | None]
    # The person behind the token: who signs what it approves (a certificate names them, with their
    # function).
    person_name: Mapped[str | None] = mapped_column(sa.String(200))
    person_function: Mapped[str | None] = mapped_column(sa.String(200))
    # SHA-256 of every other column, anchored in the audit chain at each change
    # (service/storage/rowhash.py)
    row_sha256: Mapped[str | None] = mapped_column(Sha256)


class IdempotencyKey(Base):
    """A client's Idempotency-Key of a POST route, the hash of its body and the job it created."""

    __tablename__ = "idempotency_keys"
    __table_args__ = (sa.UniqueConstraint("route", "key"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    key: Mapped[str] = mapped_column(sa.String(200))
    route: Mapped[str] = mapped_column(sa.String(100))
    request_sha256: Mapped[str] = mapped_column(Sha256)
    job_id: Mapped[int | None] = mapped_column(sa.ForeignKey("calibration_jobs.id"))
    created_at: Mapped[dt.datetime]


# ---------------------------------------------------------------- LIMS integration


class ReferenceStandard(Base):
    """One certificate of one of the lab's reference standards; a recalibration is a new row."""

    __tablename__ = "reference_standards"
    __table_args__ = (sa.UniqueConstraint("serial", "certificate_number"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(sa.String(100))
    serial: Mapped[str] = mapped_column(sa.String(100))
    model: Mapped[str | None] = mapped_column(sa.String(100))
    certificate_number: Mapped[str] = mapped_column(sa.String(100))
    certificate_sha256: Mapped[str] = mapped_column(Sha256)
    calibrated_on: Mapped[dt.date] = mapped_column(sa.Date())
    due_on: Mapped[dt.date] = mapped_column(sa.Date())
    uncertainty: Mapped[str] = mapped_column(sa.Text)  # the certificate's wording, a remark
    # U (degrees) and its coverage factor k: u = U / k enters every result calibrated against the
    # standard; empty for a standard whose stated uncertainty could not be read as an angle (refused
    # where used)
    expanded_uncertainty_deg: Mapped[float | None] = mapped_column(sa.Double())
    coverage_factor: Mapped[float | None] = mapped_column(sa.Double())
    created_at: Mapped[dt.datetime]
    created_by: Mapped[str] = mapped_column(sa.String(100))
    # The due date a standard.due_soon event was last sent for (once per due date).
    due_soon_notified_on: Mapped[dt.date | None] = mapped_column(sa.Date())
    # Who calibrated the standard: {"name", "country_code"[, "accreditation", "city"]}; certificates
    # name it.
    calibrated_by: Mapped[dict[str, str] | None] = mapped_column(sa.JSON())
    # SHA-256 of every other column, anchored in the audit chain at each change
    # (service/storage/rowhash.py)
    row_sha256: Mapped[str | None] = mapped_column(Sha256)


class Order(Base):
    """A LIMS order: what the customer wants calibrated; its state follows its jobs, records and
    certificates."""

    __tablename__ = "orders"

    id: Mapped[int] = mapped_column(primary_key=True)
    lims_order_id: Mapped[str] = mapped_column(sa.String(100), unique=True)
    item_serial: Mapped[str] = mapped_column(sa.String(100))
    # what the item is, as the customer states it: certificates name it (many instruments do not
    # report it)
    item_manufacturer: Mapped[str | None] = mapped_column(sa.String(100))
    item_model: Mapped[str | None] = mapped_column(sa.String(100))
    # {"name", "city", "country_code"[, "street", "post_code", "email"]}, as the order gave them
    customer: Mapped[dict[str, str]]
    procedure: Mapped[str] = mapped_column(sa.String(40))
    method: Mapped[str] = mapped_column(sa.String(80))
    due_on: Mapped[dt.date | None] = mapped_column(sa.Date())
    created_at: Mapped[dt.datetime]
    created_by: Mapped[str] = mapped_column(sa.String(100))
    idempotency_key: Mapped[str | None] = mapped_column(sa.String(200), unique=True)
    request_sha256: Mapped[str] = mapped_column(Sha256)
    # What the item must meet: {"max_permissible_error_deg", "decision_rule"[,
    # "guard_band_fraction", "parameters"]}; its certificate then states conformity.
    specification: Mapped[SpecificationJson | None] = mapped_column(sa.JSON())


class RecordApproval(Base):
    """A review, approval or rejection of a record: who, when, meaning, bound to the record's hash;
    chained."""

    __tablename__ = "record_approvals"
    __table_args__ = (
        sa.CheckConstraint(sa.text("decision IN ('approve', 'reject')"), name="decision"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    record_id: Mapped[int] = mapped_column(sa.ForeignKey("calibration_records.id"), index=True)
    decision: Mapped[str] = mapped_column(sa.String(16))
    # The meaning of the signature (21 CFR 11.50): "review" or "approval" for approve, "rejection"
    # for reject.
    meaning: Mapped[str] = mapped_column(sa.String(40))
    note: Mapped[str] = mapped_column(sa.Text)
    actor: Mapped[str] = mapped_column(sa.String(100))
    at: Mapped[dt.datetime]
    record_sha256: Mapped[str] = mapped_column(Sha256)
    prev_sha256: Mapped[str] = mapped_column(Sha256, unique=True)
    sha256: Mapped[str] = mapped_column(Sha256, unique=True)
    # The person who signed (the token's person at the time): part of what the approval's hash
    # covers.
    signer_name: Mapped[str | None] = mapped_column(sa.String(200))
    signer_function: Mapped[str | None] = mapped_column(sa.String(200))


class Certificate(Base):
    """Issued certificate bytes with their SHA-256: stored once, never regenerated."""

    __tablename__ = "certificates"

    id: Mapped[int] = mapped_column(primary_key=True)
    record_id: Mapped[int] = mapped_column(sa.ForeignKey("calibration_records.id"), unique=True)
    number: Mapped[str] = mapped_column(sa.String(100), unique=True)
    xml: Mapped[bytes] = mapped_column(sa.LargeBinary)
    sha256: Mapped[str] = mapped_column(Sha256)
    approval_id: Mapped[int] = mapped_column(sa.ForeignKey("record_approvals.id"))
    replaces_id: Mapped[int | None] = mapped_column(sa.ForeignKey("certificates.id"))
    issued_at: Mapped[dt.datetime]
    issued_by: Mapped[str] = mapped_column(sa.String(100))


class FeedEvent(Base):
    """One event of the LIMS feed, written in the transaction of the change it reports (id order =
    commit order)."""

    __tablename__ = "feed_events"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    type: Mapped[str] = mapped_column(sa.String(40), index=True)
    at: Mapped[dt.datetime]
    # What the event reports: its keys vary by type (the LIMS's documentation lists them).
    data: Mapped[dict[str, Any]]
    # The audit event it reports (no foreign key: the audit log's own checks must see a removal).
    audit_event_id: Mapped[int | None] = mapped_column(BigId)


class WebhookEndpoint(Base):
    __tablename__ = "webhook_endpoints"

    id: Mapped[int] = mapped_column(primary_key=True)
    url: Mapped[str] = mapped_column(sa.Text)
    events: Mapped[list[Any]]
    # The signing secret ("whsec_" + base64), needed in clear to sign; shown to the client once.
    secret: Mapped[str] = mapped_column(sa.String(100))
    created_at: Mapped[dt.datetime]
    created_by: Mapped[str] = mapped_column(sa.String(100))
    disabled_at: Mapped[dt.datetime | None]
    # SHA-256 of every other column, anchored in the audit chain at each change
    # (service/storage/rowhash.py)
    row_sha256: Mapped[str | None] = mapped_column(Sha256)


class WebhookDelivery(Base):
    """The durable outbox: one row per (endpoint, event), written with the event; retried until
    delivered."""

    __tablename__ = "webhook_deliveries"
    __table_args__ = (
        sa.UniqueConstraint("endpoint_id", "event_id"),
        sa.CheckConstraint(sa.text("state IN ('pending', 'delivered', 'failed')"), name="state"),
        sa.Index(None, "state", "next_attempt_at"),
    )

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    endpoint_id: Mapped[int] = mapped_column(sa.ForeignKey("webhook_endpoints.id"))
    event_id: Mapped[int] = mapped_column(BigId, sa.ForeignKey("feed_events.id"))
    state: Mapped[str] = mapped_column(sa.String(12))
    attempts: Mapped[int]
    next_attempt_at: Mapped[dt.datetime | None]
    last_status_code: Mapped[int | None]
    last_error: Mapped[str | None] = mapped_column(sa.Text)
    delivered_at: Mapped[dt.datetime | None]
    created_at: Mapped[dt.datetime]


class WebhookAttempt(Base):
    """The delivery log: every attempt with its answer."""

    __tablename__ = "webhook_attempts"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    delivery_id: Mapped[int] = mapped_column(
        BigId, sa.ForeignKey("webhook_deliveries.id"), index=True
    )
    at: Mapped[dt.datetime]
    status_code: Mapped[int | None]
    error: Mapped[str | None] = mapped_column(sa.Text)
    duration_s: Mapped[float] = mapped_column(sa.Double())


class Diagnosis(Base):
    """A request to run the model-discrepancy workflow on a stored record's points (never
    changed)."""

    __tablename__ = "diagnoses"

    id: Mapped[int] = mapped_column(primary_key=True)
    record_id: Mapped[int] = mapped_column(sa.ForeignKey("calibration_records.id"), index=True)
    sensor: Mapped[str] = mapped_column(sa.String(8))
    baseline: Mapped[str] = mapped_column(sa.String(20))
    created_by: Mapped[str] = mapped_column(sa.String(100))
    created_at: Mapped[dt.datetime]


class DiagnosisResult(Base):
    """How a diagnosis ended, written once: the workflow's report (JSON and its HTML page) or why it
    failed."""

    __tablename__ = "diagnosis_results"
    __table_args__ = (
        sa.CheckConstraint(sa.text("state IN ('succeeded', 'failed')"), name="state"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    diagnosis_id: Mapped[int] = mapped_column(sa.ForeignKey("diagnoses.id"), unique=True)
    state: Mapped[str] = mapped_column(sa.String(16))
    started_at: Mapped[dt.datetime | None]
    finished_at: Mapped[dt.datetime]
    # named_effects, gap_before_deg, gap_after_deg, noise_deg, steps and the full report (the
    # discrepancy workflow's document)
    summary: Mapped[dict[str, Any]] = mapped_column(default=dict)
    report_html: Mapped[str | None] = mapped_column(sa.Text)
    error: Mapped[str | None] = mapped_column(sa.Text)


_APPEND_ONLY_CLASSES = (
    CalibrationRecord,
    AuditEvent,
    ActiveCalibrationHistory,
    SettledPoint,
    RecordApproval,
    Certificate,
    FeedEvent,
    Diagnosis,
    DiagnosisResult,
)


@event.listens_for(Session, "before_flush")
def _refuse_append_only_changes(session: Session, flush_context: Any, instances: Any) -> None:
    """Refuse in the code what the triggers refuse in the database, with a clearer message."""
    for obj in list(session.dirty) + list(session.deleted):
        if isinstance(obj, _APPEND_ONLY_CLASSES) and (
            obj in session.deleted or session.is_modified(obj)
        ):
            verb = "delete" if obj in session.deleted else "update"
            raise AppendOnlyViolation(
                f"refused: {obj.__tablename__} is append-only; cannot {verb} row id={obj.id}"
                " (add a new version instead)"
            )
