"""The repository of the lab's records: every state-changing action is one transaction plus its audit event.

Each write method checks its input, writes, appends the audit event and commits, or leaves
nothing behind. Write transactions are serialised (SQLite: BEGIN IMMEDIATE; PostgreSQL: a
transaction advisory lock), which keeps the audit chain and the version numbers linear;
the unique constraints on the chains are the backstop if anything bypasses this.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from service.errors import InputError
from service.storage import samples as samples_mod
from service.storage.canonical import normalise, sha256_hex, utc_iso
from service.storage.engine import write_engine
from service.storage.errors import (
    AppendOnlyViolation,
    ConflictError,
    IllegalTransition,
    RefusedWrite,
    UnknownEntity,
)
from service.storage.models import (
    GENESIS_SHA256,
    ActiveCalibration,
    ActiveCalibrationHistory,
    AuditEvent,
    Bench,
    CalibrationJob,
    CalibrationRecord,
    Device,
    SettledPoint,
    utc_now,
)
from service.storage.models import Sample as SampleRow

_PG_WRITE_LOCK = 0x7417_1AB1

# queued -> running -> succeeded | failed | cancelled; a queued job may also be cancelled or fail to start.
TRANSITIONS: dict[str, frozenset[str]] = {
    "queued": frozenset({"running", "cancelled", "failed"}),
    "running": frozenset({"succeeded", "failed", "cancelled"}),
    "succeeded": frozenset(),
    "failed": frozenset(),
    "cancelled": frozenset(),
}
TERMINAL = frozenset(s for s, nxt in TRANSITIONS.items() if not nxt)

_POINT_FIELDS = (
    "point", "cmd_x_deg", "cmd_y_deg", "n_samples", "t_start_s", "t_end_s", "ch_x_mean", "ch_y_mean",
    "ch_z_mean", "ch_x_std", "ch_y_std", "ch_z_std", "temp_c_mean",
)  # fmt: skip
_POINT_REQUIRED = ("point", "n_samples", "t_start_s", "t_end_s", "ch_x_mean", "ch_y_mean")
_UNSET: Any = object()


# ---------------------------------------------------------------- hashing rules


def record_content(r: CalibrationRecord) -> dict[str, Any]:
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


def audit_content(e: AuditEvent) -> dict[str, Any]:
    return {
        "at": utc_iso(e.at),
        "actor": e.actor,
        "action": e.action,
        "entity": e.entity,
        "entity_id": e.entity_id,
        "details": e.details,
        "prev_sha256": e.prev_sha256,
    }


def point_content(p: SettledPoint) -> dict[str, Any]:
    return {name: getattr(p, name) for name in _POINT_FIELDS}


def points_sha256(points: Sequence[SettledPoint]) -> str:
    return sha256_hex([point_content(p) for p in sorted(points, key=lambda p: p.point)])


# ---------------------------------------------------------------- input checks


def _text(name: str, value: object, max_len: int = 100) -> str:
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"{name} must be a non-empty string")
    if len(value) > max_len:
        raise InputError(f"{name} is longer than {max_len} characters")
    return value


def _optional_text(name: str, value: object, max_len: int) -> str | None:
    return None if value is None else _text(name, value, max_len)


def _finite(name: str, value: object, *, optional: bool = True) -> float | None:
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise InputError(f"{name}={value!r} is not a finite number")
    return float(value)


def _doc(name: str, value: object) -> dict[str, Any]:
    if not isinstance(value, Mapping):
        raise InputError(f"{name} must be a JSON object (dict)")
    return normalise(dict(value))


def _standards(value: object) -> list[dict[str, Any]]:
    if not isinstance(value, list | tuple):
        raise InputError("reference_standards must be a list of {name, serial, certificate_id}")
    out = []
    for i, item in enumerate(value):
        if not isinstance(item, Mapping):
            raise InputError(f"reference_standards[{i}] must be an object")
        cert = item.get("certificate_id")
        if not isinstance(cert, str) or not cert.strip():
            raise InputError(f"reference_standards[{i}] has no certificate_id: traceability needs it")
        if not (item.get("name") or item.get("serial")):
            raise InputError(f"reference_standards[{i}] needs a name or a serial")
        out.append(dict(item))
    return normalise(out)


def _translate(exc: sa.exc.DBAPIError) -> RefusedWrite:
    orig = exc.orig
    message = str(orig).strip().splitlines()[0] if orig is not None else str(exc)
    code = getattr(orig, "sqlstate", None)
    lower = message.lower()
    if "append-only" in lower or "raw data" in lower or "are kept" in lower:
        return AppendOnlyViolation(f"refused by the database: {message}")
    if code == "23503" or "foreign key" in lower:
        return UnknownEntity(f"refused by the database: a referenced row does not exist ({message})")
    if code == "23505" or "unique" in lower:
        return ConflictError(f"refused by the database: duplicate ({message})")
    return RefusedWrite(f"refused by the database: {message}")


# ---------------------------------------------------------------- the store


class Store:
    def __init__(self, engine: sa.Engine) -> None:
        self.engine = engine
        self._read = sessionmaker(bind=engine, expire_on_commit=False)
        self._write = sessionmaker(bind=write_engine(engine), expire_on_commit=False)

    @contextmanager
    def session(self) -> Iterator[Session]:
        """A read session (or for callers composing their own work; flushes still pass the append-only guard)."""
        with self._read() as s:
            yield s

    @contextmanager
    def _tx(self) -> Iterator[Session]:
        with self._write() as s:
            try:
                with s.begin():
                    if s.bind.dialect.name == "postgresql":  # type: ignore[union-attr]
                        s.execute(sa.text("SELECT pg_advisory_xact_lock(:k)"), {"k": _PG_WRITE_LOCK})
                    yield s
            except (sa.exc.IntegrityError, sa.exc.DataError) as exc:  # the guard triggers' refusals included
                raise _translate(exc) from exc

    # ------------------------------------------------------------ audit

    def _audit(self, s: Session, actor: str, action: str, entity: str, entity_id: object, details: Mapping) -> AuditEvent:
        s.flush()  # the action's rows first, so their ids are known and constraints have run
        prev = s.execute(sa.select(AuditEvent.sha256).order_by(AuditEvent.id.desc()).limit(1)).scalar()
        event = AuditEvent(
            at=utc_now(),
            actor=_text("actor", actor),
            action=action,
            entity=entity,
            entity_id=str(entity_id),
            details=normalise(dict(details)),
            prev_sha256=prev or GENESIS_SHA256,
        )
        event.sha256 = sha256_hex(audit_content(event))
        s.add(event)
        s.flush()
        return event

    def audit_events(self, *, entity: str | None = None, entity_id: object = None, limit: int = 1000) -> list[AuditEvent]:
        with self._read() as s:
            stmt = sa.select(AuditEvent).order_by(AuditEvent.id.desc()).limit(limit)
            if entity is not None:
                stmt = stmt.where(AuditEvent.entity == entity)
            if entity_id is not None:
                stmt = stmt.where(AuditEvent.entity_id == str(entity_id))
            return list(s.scalars(stmt))

    # ------------------------------------------------------------ benches and devices

    def add_bench(
        self,
        name: str,
        *,
        actor: str,
        stage_model: str | None = None,
        stage_serial: str | None = None,
        port: str | None = None,
        port_settings: Mapping | None = None,
    ) -> Bench:
        with self._tx() as s:
            name = _text("bench name", name)
            if s.scalar(sa.select(Bench.id).where(Bench.name == name)) is not None:
                raise ConflictError(f"a bench named {name!r} already exists")
            port = _optional_text("port", port, 200)
            bench = Bench(
                name=name,
                stage_model=_optional_text("stage_model", stage_model, 100),
                stage_serial=_optional_text("stage_serial", stage_serial, 100),
                port=port,
                port_settings=_doc("port_settings", port_settings or {}),
            )
            s.add(bench)
            s.flush()
            self._audit(s, actor, "bench.create", "bench", bench.id, {"name": name, "port": port})
            return bench

    def add_device(
        self,
        model: str,
        serial: str,
        role: str,
        *,
        actor: str,
        bench_id: int | None = None,
        port: str | None = None,
        port_settings: Mapping | None = None,
    ) -> Device:
        with self._tx() as s:
            model, serial, role = _text("model", model), _text("serial", serial), _text("role", role, 40)
            port = _optional_text("port", port, 200)
            if bench_id is not None and s.get(Bench, bench_id) is None:
                raise UnknownEntity(f"bench {bench_id} does not exist")
            existing = s.scalar(sa.select(Device.id).where(Device.model == model, Device.serial == serial))
            if existing is not None:
                raise ConflictError(f"device {model} s/n {serial} already exists (id {existing})")
            device = Device(
                model=model,
                serial=serial,
                role=role,
                bench_id=bench_id,
                port=port,
                port_settings=_doc("port_settings", port_settings or {}),
            )
            s.add(device)
            s.flush()
            self._audit(
                s, actor, "device.create", "device", device.id,
                {"model": model, "serial": serial, "role": role, "bench_id": bench_id, "port": port},
            )  # fmt: skip
            return device

    def update_device(self, device_id: int, *, actor: str, **changes: Any) -> Device:
        allowed = {"role", "bench_id", "port", "port_settings"}
        unknown = set(changes) - allowed
        if unknown:
            raise InputError(f"cannot change {sorted(unknown)} of a device; changeable: {sorted(allowed)}")
        with self._tx() as s:
            device = self._device(s, device_id)
            if changes.get("bench_id") is not None and s.get(Bench, changes["bench_id"]) is None:
                raise UnknownEntity(f"bench {changes['bench_id']} does not exist")
            if "role" in changes:
                changes["role"] = _text("role", changes["role"], 40)
            if "port" in changes:
                changes["port"] = _optional_text("port", changes["port"], 200)
            if "port_settings" in changes:
                changes["port_settings"] = _doc("port_settings", changes["port_settings"] or {})
            before = {k: getattr(device, k) for k in changes}
            for key, value in changes.items():
                setattr(device, key, value)
            self._audit(s, actor, "device.update", "device", device.id, {"before": before, "after": changes})
            return device

    def _device(self, s: Session, device_id: int) -> Device:
        device = s.get(Device, device_id) if isinstance(device_id, int) else None
        if device is None:
            raise UnknownEntity(f"device {device_id!r} does not exist")
        return device

    def get_device(self, device_id: int) -> Device:
        with self._read() as s:
            return self._device(s, device_id)

    def find_device(self, model: str, serial: str) -> Device | None:
        with self._read() as s:
            return s.scalar(sa.select(Device).where(Device.model == model, Device.serial == serial))

    def devices(self) -> list[Device]:
        with self._read() as s:
            return list(s.scalars(sa.select(Device).order_by(Device.id)))

    def benches(self) -> list[Bench]:
        with self._read() as s:
            return list(s.scalars(sa.select(Bench).order_by(Bench.id)))

    # ------------------------------------------------------------ jobs

    def create_job(
        self,
        device_id: int,
        kind: str,
        method: str,
        *,
        actor: str,
        parameters: Mapping | None = None,
        bench_id: int | None = None,
    ) -> CalibrationJob:
        with self._tx() as s:
            self._device(s, device_id)
            if bench_id is not None and s.get(Bench, bench_id) is None:
                raise UnknownEntity(f"bench {bench_id} does not exist")
            job = CalibrationJob(
                device_id=device_id,
                bench_id=bench_id,
                kind=_text("kind", kind, 40),
                method=_text("method", method, 80),
                state="queued",
                progress=0.0,
                parameters=_doc("parameters", parameters or {}),
                created_by=_text("actor", actor),
            )
            s.add(job)
            s.flush()
            self._audit(s, actor, "job.create", "job", job.id, {"device_id": device_id, "kind": kind, "method": method})
            return job

    def _job(self, s: Session, job_id: int) -> CalibrationJob:
        job = s.get(CalibrationJob, job_id) if isinstance(job_id, int) else None
        if job is None:
            raise UnknownEntity(f"job {job_id!r} does not exist")
        return job

    def get_job(self, job_id: int) -> CalibrationJob:
        with self._read() as s:
            return self._job(s, job_id)

    def jobs(self, *, state: str | None = None) -> list[CalibrationJob]:
        with self._read() as s:
            stmt = sa.select(CalibrationJob).order_by(CalibrationJob.id)
            if state is not None:
                stmt = stmt.where(CalibrationJob.state == state)
            return list(s.scalars(stmt))

    def transition_job(
        self, job_id: int, to_state: str, *, actor: str, failure_reason: str | None = None
    ) -> CalibrationJob:
        if to_state not in TRANSITIONS:
            raise InputError(f"job state {to_state!r} is not one of {sorted(TRANSITIONS)}")
        with self._tx() as s:
            job = self._job(s, job_id)
            if to_state not in TRANSITIONS[job.state]:
                allowed = ", ".join(sorted(TRANSITIONS[job.state])) or "none (terminal state)"
                raise IllegalTransition(f"job {job_id}: {job.state} -> {to_state} is not allowed; allowed: {allowed}")
            if to_state == "failed":
                failure_reason = _text("failure_reason", failure_reason, 10_000)
            elif failure_reason is not None and to_state != "cancelled":
                raise InputError(f"a failure_reason belongs to a failed or cancelled job, not {to_state}")
            now = utc_now()
            previous = job.state
            job.state = to_state
            if to_state == "running":
                job.started_at = now
            if to_state in TERMINAL:
                job.finished_at = now
                job.failure_reason = failure_reason
                if to_state == "succeeded":
                    job.progress = 1.0
            self._audit(
                s, actor, f"job.{to_state}", "job", job.id,
                {"from": previous, "to": to_state, "failure_reason": failure_reason},
            )  # fmt: skip
            return job

    def start_job(self, job_id: int, *, actor: str) -> CalibrationJob:
        return self.transition_job(job_id, "running", actor=actor)

    def succeed_job(self, job_id: int, *, actor: str) -> CalibrationJob:
        return self.transition_job(job_id, "succeeded", actor=actor)

    def fail_job(self, job_id: int, reason: str, *, actor: str) -> CalibrationJob:
        return self.transition_job(job_id, "failed", actor=actor, failure_reason=reason)

    def cancel_job(self, job_id: int, *, actor: str, reason: str | None = None) -> CalibrationJob:
        return self.transition_job(job_id, "cancelled", actor=actor, failure_reason=reason)

    def set_progress(self, job_id: int, progress: float) -> None:
        """Progress of a running job in [0, 1]; not audited (it is not a decision, only a gauge)."""
        value = _finite("progress", progress, optional=False)
        if not 0.0 <= value <= 1.0:  # type: ignore[operator]
            raise InputError(f"progress {progress} is outside [0, 1]")
        with self._tx() as s:
            job = self._job(s, job_id)
            if job.state != "running":
                raise IllegalTransition(f"job {job_id} is {job.state}; progress is only kept for running jobs")
            job.progress = value  # type: ignore[assignment]

    # ------------------------------------------------------------ settled points

    def add_settled_points(
        self, job_id: int, device_id: int, points: Sequence[Mapping[str, Any]], *, actor: str
    ) -> list[SettledPoint]:
        with self._tx() as s:
            job = self._job(s, job_id)
            self._device(s, device_id)
            if job.state != "running":
                raise IllegalTransition(f"job {job_id} is {job.state}; settled points are added while it runs")
            rows = []
            for i, p in enumerate(points):
                unknown = set(p) - set(_POINT_FIELDS)
                missing = [k for k in _POINT_REQUIRED if p.get(k) is None]
                if unknown or missing:
                    raise InputError(f"settled point [{i}]: unknown fields {sorted(unknown)}, missing {missing}")
                values: dict[str, Any] = {}
                for k in _POINT_FIELDS:
                    if k in ("point", "n_samples"):
                        if not isinstance(p[k], int) or p[k] < 0:
                            raise InputError(f"settled point [{i}]: {k} must be a non-negative integer")
                        values[k] = p[k]
                    else:
                        values[k] = _finite(f"settled point [{i}] {k}", p.get(k))
                rows.append(SettledPoint(job_id=job_id, device_id=device_id, **values))
            s.add_all(rows)
            s.flush()
            self._audit(
                s, actor, "points.add", "job", job_id,
                {"device_id": device_id, "count": len(rows), "points": [r.point for r in rows],
                 "points_sha256": sha256_hex([point_content(r) for r in sorted(rows, key=lambda r: r.point)])},
            )  # fmt: skip
            return rows

    def settle_from_samples(
        self, job_id: int, device_id: int, *, actor: str, skip_s: float = 0.0,
        commands: Mapping[int, tuple[float, float]] | None = None,
    ) -> list[SettledPoint]:  # fmt: skip
        """Average each grid point's raw samples after discarding the first skip_s seconds (settling)."""
        skip_s = _finite("skip_s", skip_s, optional=False)  # type: ignore[assignment]
        if skip_s < 0:
            raise InputError(f"skip_s={skip_s} is negative; it is the settling time discarded at each point")
        with self._read() as s:
            t = SampleRow.__table__
            rows = s.execute(
                sa.select(t.c.point, t.c.t_s, t.c.ch_x, t.c.ch_y, t.c.ch_z, t.c.temp_c)
                .where(t.c.job_id == job_id, t.c.device_id == device_id, t.c.point.is_not(None))
                .order_by(t.c.point, t.c.t_s)
            ).all()
        by_point: dict[int, list[Any]] = {}
        for r in rows:
            by_point.setdefault(r.point, []).append(r)
        points = []
        for point, rs in sorted(by_point.items()):
            t0 = rs[0].t_s + skip_s
            rs = [r for r in rs if r.t_s >= t0]
            if not rs:
                continue
            cmd = (commands or {}).get(point, (None, None))
            points.append({
                "point": point, "cmd_x_deg": cmd[0], "cmd_y_deg": cmd[1], "n_samples": len(rs),
                "t_start_s": rs[0].t_s, "t_end_s": rs[-1].t_s,
                "ch_x_mean": _mean([r.ch_x for r in rs]), "ch_y_mean": _mean([r.ch_y for r in rs]),
                "ch_z_mean": _mean([r.ch_z for r in rs]), "ch_x_std": _std([r.ch_x for r in rs]),
                "ch_y_std": _std([r.ch_y for r in rs]), "ch_z_std": _std([r.ch_z for r in rs]),
                "temp_c_mean": _mean([r.temp_c for r in rs]),
            })  # fmt: skip
        if not points:
            raise InputError(f"job {job_id} has no raw samples of device {device_id} with a grid point")
        return self.add_settled_points(job_id, device_id, points, actor=actor)

    def settled_points(self, job_id: int, device_id: int | None = None) -> list[SettledPoint]:
        with self._read() as s:
            stmt = sa.select(SettledPoint).where(SettledPoint.job_id == job_id)
            if device_id is not None:
                stmt = stmt.where(SettledPoint.device_id == device_id)
            return list(s.scalars(stmt.order_by(SettledPoint.device_id, SettledPoint.point)))

    # ------------------------------------------------------------ calibration records

    def add_record(
        self,
        device_id: int,
        kind: str,
        method: str,
        model: Mapping[str, Any],
        *,
        operator: str,
        reference_standards: Sequence[Mapping[str, Any]] = (),
        validation: Mapping[str, Any] | None = None,
        temp_c: float | None = None,
        job_id: int | None = None,
        raw_data: Mapping[str, Any] | None = None,
        supersedes_id: int | None = _UNSET,
        activate: bool = False,
        reason: str | None = None,
    ) -> CalibrationRecord:
        """Append a new version for (device, kind). By default it supersedes the active version.

        With activate=True the new version also becomes the active one in the same transaction.
        """
        with self._tx() as s:
            self._device(s, device_id)
            kind, method = _text("kind", kind, 40), _text("method", method, 80)
            operator = _text("operator", operator)
            model_doc = _doc("model", model)
            for key, expected in (("kind", kind), ("method", method)):
                if key in model_doc and model_doc[key] != expected:
                    raise InputError(f"model document says {key}={model_doc[key]!r} but the record is {expected!r}")
            raw = _doc("raw_data", raw_data or {})
            if job_id is not None:
                job = self._job(s, job_id)
                if job.device_id != device_id:
                    raise InputError(f"job {job_id} calibrates device {job.device_id}, not device {device_id}")
                if job.state not in ("running", "succeeded"):
                    raise IllegalTransition(f"job {job_id} is {job.state}; a record comes from a running or succeeded job")
                pts = list(s.scalars(sa.select(SettledPoint).where(
                    SettledPoint.job_id == job_id, SettledPoint.device_id == device_id)))  # fmt: skip
                n_samples = s.scalar(
                    sa.select(sa.func.count()).select_from(SampleRow)
                    .where(SampleRow.job_id == job_id, SampleRow.device_id == device_id)
                )  # fmt: skip
                raw.update({"job_id": job_id, "points": len(pts), "points_sha256": points_sha256(pts), "samples": n_samples})
            active = s.get(ActiveCalibration, (device_id, kind))
            if supersedes_id is _UNSET:
                supersedes_id = active.record_id if active else None
            elif supersedes_id is not None:
                old = s.get(CalibrationRecord, supersedes_id)
                if old is None or (old.device_id, old.kind) != (device_id, kind):
                    raise UnknownEntity(f"record {supersedes_id} is not a {kind} record of device {device_id}")
            last = s.execute(
                sa.select(CalibrationRecord.version, CalibrationRecord.content_sha256)
                .where(CalibrationRecord.device_id == device_id, CalibrationRecord.kind == kind)
                .order_by(CalibrationRecord.version.desc()).limit(1)
            ).first()  # fmt: skip
            record = CalibrationRecord(
                device_id=device_id,
                kind=kind,
                version=(last.version + 1) if last else 1,
                content_format=1,
                method=method,
                model=model_doc,
                validation=_doc("validation", validation or {}),
                temp_c=_finite("temp_c", temp_c),
                reference_standards=_standards(list(reference_standards)),
                operator=operator,
                created_at=utc_now(),
                job_id=job_id,
                raw_data=raw,
                supersedes_id=supersedes_id,
                prev_sha256=last.content_sha256 if last else GENESIS_SHA256,
            )
            record.content_sha256 = sha256_hex(record_content(record))
            s.add(record)
            s.flush()
            self._audit(
                s, operator, "record.create", "calibration_record", record.id,
                {"device_id": device_id, "kind": kind, "version": record.version,
                 "content_sha256": record.content_sha256, "supersedes_id": supersedes_id},
            )  # fmt: skip
            if activate:
                self._activate(s, record, actor=operator, reason=reason or f"new version {record.version}",
                               replaces=active.record_id if active else None)  # fmt: skip
            return record

    def get_record(self, record_id: int) -> CalibrationRecord:
        with self._read() as s:
            record = s.get(CalibrationRecord, record_id)
            if record is None:
                raise UnknownEntity(f"calibration record {record_id} does not exist")
            return record

    def records(self, device_id: int, kind: str | None = None) -> list[CalibrationRecord]:
        with self._read() as s:
            stmt = sa.select(CalibrationRecord).where(CalibrationRecord.device_id == device_id)
            if kind is not None:
                stmt = stmt.where(CalibrationRecord.kind == kind)
            return list(s.scalars(stmt.order_by(CalibrationRecord.kind, CalibrationRecord.version)))

    def active_record(self, device_id: int, kind: str) -> CalibrationRecord | None:
        with self._read() as s:
            return s.scalar(
                sa.select(CalibrationRecord).join(
                    ActiveCalibration, ActiveCalibration.record_id == CalibrationRecord.id
                ).where(ActiveCalibration.device_id == device_id, ActiveCalibration.kind == kind)
            )  # fmt: skip

    def pointer_history(self, device_id: int, kind: str) -> list[ActiveCalibrationHistory]:
        with self._read() as s:
            return list(s.scalars(
                sa.select(ActiveCalibrationHistory)
                .where(ActiveCalibrationHistory.device_id == device_id, ActiveCalibrationHistory.kind == kind)
                .order_by(ActiveCalibrationHistory.id)
            ))  # fmt: skip

    # ------------------------------------------------------------ the active pointer

    def activate(self, record_id: int, *, actor: str, reason: str, replaces: int | None = None) -> ActiveCalibration:
        """Make a record the active version of its (device, kind).

        `replaces` names the record the caller believes is active now (None: none is). If another
        one is active the change is refused: there is never a second active pointer, and a switch
        is always a deliberate, audited act.
        """
        with self._tx() as s:
            record = s.get(CalibrationRecord, record_id) if isinstance(record_id, int) else None
            if record is None:
                raise UnknownEntity(f"calibration record {record_id!r} does not exist")
            return self._activate(s, record, actor=actor, reason=reason, replaces=replaces)

    def _activate(
        self, s: Session, record: CalibrationRecord, *, actor: str, reason: str, replaces: int | None
    ) -> ActiveCalibration:
        actor, reason = _text("actor", actor), _text("reason", reason, 10_000)
        if sha256_hex(record_content(record)) != record.content_sha256:
            raise RefusedWrite(f"record {record.id} does not match its hash (tampered); it cannot be activated")
        current = s.get(ActiveCalibration, (record.device_id, record.kind))
        current_id = current.record_id if current else None
        if current_id != replaces:
            if current is None:
                raise ConflictError(
                    f"device {record.device_id} has no active {record.kind} calibration, not record {replaces}"
                )
            raise ConflictError(
                f"device {record.device_id} already has an active {record.kind} calibration (record {current_id});"
                f" a second active pointer is refused: pass replaces={current_id} to switch to record {record.id}"
            )
        now = utc_now()
        if current is None:
            current = ActiveCalibration(
                device_id=record.device_id, kind=record.kind, record_id=record.id, set_at=now, set_by=actor, reason=reason
            )
            s.add(current)
        else:
            current.record_id, current.set_at, current.set_by, current.reason = record.id, now, actor, reason
        s.add(ActiveCalibrationHistory(
            device_id=record.device_id, kind=record.kind, record_id=record.id, previous_record_id=current_id,
            changed_at=now, changed_by=actor, reason=reason,
        ))  # fmt: skip
        self._audit(
            s, actor, "pointer.set", "active_calibration", f"{record.device_id}/{record.kind}",
            {"record_id": record.id, "version": record.version, "previous_record_id": current_id,
             "content_sha256": record.content_sha256, "reason": reason},
        )  # fmt: skip
        return current

    def deactivate(self, device_id: int, kind: str, *, actor: str, reason: str, replaces: int) -> None:
        """Withdraw the active version (e.g. the device failed validation); audited like a switch."""
        with self._tx() as s:
            actor, reason = _text("actor", actor), _text("reason", reason, 10_000)
            current = s.get(ActiveCalibration, (device_id, kind))
            if current is None or current.record_id != replaces:
                raise ConflictError(
                    f"device {device_id} {kind}: active record is {current.record_id if current else None}, not {replaces}"
                )
            s.delete(current)
            s.add(ActiveCalibrationHistory(
                device_id=device_id, kind=kind, record_id=None, previous_record_id=replaces,
                changed_at=utc_now(), changed_by=actor, reason=reason,
            ))  # fmt: skip
            self._audit(s, actor, "pointer.clear", "active_calibration", f"{device_id}/{kind}",
                        {"record_id": None, "previous_record_id": replaces, "reason": reason})  # fmt: skip

    # ------------------------------------------------------------ retention

    def apply_retention(
        self,
        *,
        actor: str,
        older_than: dt.timedelta,
        policy: str = "thin",
        thin_interval_s: float = 60.0,
        now: dt.datetime | None = None,
    ) -> samples_mod.RetentionResult:
        with self._tx() as s:
            result = samples_mod.apply_retention(
                s.connection(), older_than=older_than, policy=policy, thin_interval_s=thin_interval_s, now=now
            )
            self._audit(
                s, actor, "retention.apply", "samples", "monitoring",
                {"policy": policy, "cutoff_s": result.cutoff_s, "deleted": result.deleted,
                 "thin_interval_s": thin_interval_s if policy == "thin" else None},
            )  # fmt: skip
            return result

    def apply_retention_from_settings(self, settings, *, actor: str = "retention") -> samples_mod.RetentionResult:  # type: ignore[no-untyped-def]
        return self.apply_retention(
            actor=actor,
            older_than=dt.timedelta(days=settings.monitoring_retention_days),
            policy=settings.monitoring_retention_policy,
            thin_interval_s=settings.monitoring_thin_interval_s,
        )


def _mean(values: Sequence[float | None]) -> float | None:
    if any(v is None for v in values) or not values:
        return None
    return math.fsum(values) / len(values)  # type: ignore[arg-type]


def _std(values: Sequence[float | None]) -> float | None:
    """Sample standard deviation (n - 1), two-pass for precision."""
    if len(values) < 2 or any(v is None for v in values):
        return None
    m = math.fsum(values) / len(values)  # type: ignore[arg-type]
    return math.sqrt(math.fsum((v - m) ** 2 for v in values) / (len(values) - 1))  # type: ignore[operator]
