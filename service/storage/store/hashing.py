"""What a record, an audit event and a settled point assert: the content their SHA-256 covers (rule
in canonical.py)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NotRequired, TypedDict

from service.storage.canonical import sha256_hex, utc_iso
from service.storage.models import AuditEvent, CalibrationRecord, SettledPoint

POINT_FIELDS = (
    "point",
    "cmd_x_deg",
    "cmd_y_deg",
    "n_samples",
    "t_start_s",
    "t_end_s",
    "ch_x_mean",
    "ch_y_mean",
    "ch_z_mean",
    "ch_x_std",
    "ch_y_std",
    "ch_z_std",
    "temp_c_mean",
)
POINT_REQUIRED = ("point", "n_samples", "t_start_s", "t_end_s", "ch_x_mean", "ch_y_mean")


class SettledPointFields(TypedDict):
    """A settled point's fields (POINT_FIELDS), as given or averaged from samples, with the hash of
    the raw samples it came from once that is known."""

    point: int
    cmd_x_deg: float | None
    cmd_y_deg: float | None
    n_samples: int
    t_start_s: float | None
    t_end_s: float | None
    ch_x_mean: float | None
    ch_y_mean: float | None
    ch_z_mean: float | None
    ch_x_std: float | None
    ch_y_std: float | None
    ch_z_std: float | None
    temp_c_mean: float | None
    samples_sha256: NotRequired[str | None]


class RecordContent(TypedDict):
    """Everything a record asserts (its JSON documents as stored), hashed into `content_sha256`."""

    content_format: int
    device_id: int
    kind: str
    version: int
    method: str
    model: Mapping[str, object]
    validation: Mapping[str, object]
    temp_c: float | None
    reference_standards: Sequence[object]
    operator: str
    created_at: str
    job_id: int | None
    raw_data: Mapping[str, object]
    supersedes_id: int | None
    prev_sha256: str


class AuditContent(TypedDict):
    """What an audit event asserts, hashed into its `sha256`."""

    at: str
    actor: str
    action: str
    entity: str
    entity_id: str
    details: Mapping[str, object]
    prev_sha256: str


# What a settled point asserts: its POINT_FIELDS and, where kept, its samples' "samples_sha256".
PointContent = dict[str, int | float | str | None]


def record_content(r: CalibrationRecord) -> RecordContent:
    """Everything a record asserts; its SHA-256 is `content_sha256` (rule in canonical.py)."""
    return {
        "content_format": r.content_format,
        "device_id": r.device_id,
        "kind": r.kind,
        "version": r.version,
        "method": r.method,
        "model": r.model,
        "validation": r.validation,
        "temp_c": r.temp_c,
        "reference_standards": r.reference_standards,
        "operator": r.operator,
        "created_at": utc_iso(r.created_at),
        "job_id": r.job_id,
        "raw_data": r.raw_data,
        "supersedes_id": r.supersedes_id,
        "prev_sha256": r.prev_sha256,
    }


def audit_content(e: AuditEvent) -> AuditContent:
    return {
        "at": utc_iso(e.at),
        "actor": e.actor,
        "action": e.action,
        "entity": e.entity,
        "entity_id": e.entity_id,
        "details": e.details,
        "prev_sha256": e.prev_sha256,
    }


def point_content(p: SettledPoint) -> PointContent:
    """What a settled point asserts: its fields, and the hash of the raw samples it was averaged
    from (points stored before those hashes were kept have none, and hash as they did)."""
    content: PointContent = {name: getattr(p, name) for name in POINT_FIELDS}
    if p.samples_sha256 is not None:
        content["samples_sha256"] = p.samples_sha256
    return content


SAMPLE_FIELDS = ("t_s", "ch_x", "ch_y", "ch_z", "temp_c", "source")


def samples_sha256(rows: Sequence[Sequence[Any]]) -> str:
    """The SHA-256 of one point's raw samples of one device: rows of SAMPLE_FIELDS in (t_s, id)
    order, numbers as floats (as the database gives them back)."""
    return sha256_hex(
        [
            [
                None if value is None else (value if isinstance(value, str) else float(value))
                for value in row
            ]
            for row in rows
        ]
    )


def points_sha256(points: Sequence[SettledPoint]) -> str:
    return sha256_hex(
        [point_content(point) for point in sorted(points, key=lambda point: point.point)]
    )
