"""Reference standards: registered with their certificate's SHA-256 and stated uncertainty, refused
when a job names one past its due date, announced once when their due date comes near."""

from __future__ import annotations

import datetime as dt
import math
import re
from collections.abc import Mapping, Sequence

import sqlalchemy as sa

from service.errors import InputError
from service.storage.errors import ConflictError
from service.storage.models import ReferenceStandard, utc_now
from service.storage.stated_uncertainty import parse_stated_uncertainty
from service.storage.store.checks import require_date, require_text
from service.storage.store.database import Database
from service.storage.store.lookups import row_in

CERTIFICATE_SHA256 = re.compile(r"[0-9a-f]{64}")


class StandardNotUsable(InputError):
    """A job names a reference standard past its due date (or one that does not exist); `field` says
    which."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f"{field}: {reason}")
        self.field, self.reason = field, reason


def positive_number(
    name: str, value: object, *, above: float | None = None, least: float | None = None
) -> float:
    ok = (
        not isinstance(value, bool)
        and isinstance(value, int | float)
        and math.isfinite(value)
        and (above is None or value > above)
        and (least is None or value >= least)
    )
    if not ok:
        raise InputError(
            f"{name}: {value!r} is not a number "
            f"{f'> {above:g}' if above is not None else f'>= {least:g}'}"
        )
    return float(value)  # type: ignore[arg-type]


def stated_uncertainty(
    fields: Mapping[str, object], remark: str
) -> tuple[float | None, float | None]:
    """U (degrees) and k as given, else read from the remark's wording; (None, None) when neither
    says."""
    expanded_deg, k = fields.get("expanded_uncertainty_deg"), fields.get("coverage_factor")
    if expanded_deg is None:
        if k is not None:
            raise InputError("coverage_factor: given without expanded_uncertainty_deg")
        parsed = parse_stated_uncertainty(remark)
        return parsed if parsed is not None else (None, None)
    return (
        positive_number("expanded_uncertainty_deg", expanded_deg, above=0.0),
        positive_number("coverage_factor", 2.0 if k is None else k, least=1.0),
    )


CALIBRATED_BY_FIELDS = {"name": 200, "accreditation": 100, "city": 200, "country_code": 2}


def calibrated_by_of(value: object) -> dict[str, str] | None:
    """Who calibrated a standard: {"name", "country_code"[, "accreditation", "city"]}, checked; None
    when not given."""
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise InputError(
            'calibrated_by: an object {"name", "accreditation", "city", "country_code"} is needed'
        )
    unknown = sorted(set(value) - set(CALIBRATED_BY_FIELDS))
    if unknown:
        raise InputError(
            f"calibrated_by.{unknown[0]}: unknown; give {', '.join(CALIBRATED_BY_FIELDS)}"
        )
    out: dict[str, str] = {}
    for key, longest in CALIBRATED_BY_FIELDS.items():
        text = value.get(key)
        if text is None and key in ("accreditation", "city"):
            continue
        out[key] = require_text(f"calibrated_by.{key}", text, longest).strip()
    if not re.fullmatch(r"[A-Z]{2}", out["country_code"]):
        raise InputError("calibrated_by.country_code must be two upper-case letters (ISO 3166-1)")
    return out


class StandardsRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def add_standard(self, fields: Mapping[str, object], *, actor: str) -> ReferenceStandard:
        sha = fields.get("certificate_sha256")
        if not isinstance(sha, str) or not CERTIFICATE_SHA256.fullmatch(sha):
            raise InputError(
                "certificate_sha256 must be the 64 lower-case hex digits of the certificate file's "
                "SHA-256"
            )
        calibrated, due = (
            require_date("calibrated_on", fields.get("calibrated_on")),
            require_date("due_on", fields.get("due_on")),
        )
        if due <= calibrated:
            raise InputError(f"due_on {due} must be after calibrated_on {calibrated}")
        model = fields.get("model")
        remark = fields.get("uncertainty")
        remark = require_text("uncertainty", remark, 500) if remark not in (None, "") else ""
        expanded_deg, k = stated_uncertainty(fields, remark)
        row = ReferenceStandard(
            name=require_text("name", fields.get("name")),
            serial=require_text("serial", fields.get("serial")),
            model=require_text("model", model) if model is not None else None,
            certificate_number=require_text("certificate_number", fields.get("certificate_number")),
            certificate_sha256=sha,
            calibrated_on=calibrated,
            due_on=due,
            uncertainty=remark,
            expanded_uncertainty_deg=expanded_deg,
            coverage_factor=k,
            created_at=utc_now(),
            created_by=require_text("actor", actor),
            calibrated_by=calibrated_by_of(fields.get("calibrated_by")),
        )
        with self._db.transaction() as session:
            clash = session.scalar(
                sa.select(ReferenceStandard.id).where(
                    ReferenceStandard.serial == row.serial,
                    ReferenceStandard.certificate_number == row.certificate_number,
                )
            )
            if clash is not None:
                raise ConflictError(
                    f"standard {clash} already holds certificate {row.certificate_number} of "
                    f"serial {row.serial}"
                )
            session.add(row)
            session.flush()
            self._db.audit(
                session,
                actor,
                "standard.create",
                "reference_standard",
                row.id,
                {
                    "name": row.name,
                    "serial": row.serial,
                    "certificate_number": row.certificate_number,
                    "certificate_sha256": sha,
                    "due_on": due.isoformat(),
                    "expanded_uncertainty_deg": expanded_deg,
                    "coverage_factor": k,
                    "calibrated_by": row.calibrated_by,
                },
            )
            return row

    def all(self) -> list[ReferenceStandard]:
        with self._db.session() as session:
            return list(
                session.scalars(sa.select(ReferenceStandard).order_by(ReferenceStandard.id))
            )

    def page(self, *, after_id: int | None = None, limit: int = 50) -> list[ReferenceStandard]:
        """Standards in id order from after `after_id` (the cursor), at most `limit`."""
        with self._db.session() as session:
            stmt = sa.select(ReferenceStandard).order_by(ReferenceStandard.id).limit(limit)
            if after_id is not None:
                stmt = stmt.where(ReferenceStandard.id > after_id)
            return list(session.scalars(stmt))

    def get(self, standard_id: int) -> ReferenceStandard:
        with self._db.session() as session:
            return row_in(session, ReferenceStandard, standard_id, "reference standard")

    def usable_standards(self, ids: Sequence[object], *, on: dt.date) -> list[ReferenceStandard]:
        """The standards a job names, refused if one is unknown or past its due date on `on`."""
        if not isinstance(ids, list | tuple):
            raise StandardNotUsable(
                "reference_standards", "must be a list of reference standard ids"
            )
        out: list[ReferenceStandard] = []
        with self._db.session() as session:
            for i, sid in enumerate(ids):
                row = (
                    session.get(ReferenceStandard, sid)
                    if isinstance(sid, int) and not isinstance(sid, bool)
                    else None
                )
                if row is None:
                    raise StandardNotUsable(
                        f"reference_standards[{i}]",
                        f"{sid!r} is not a registered reference standard",
                    )
                if row.due_on < on:
                    raise StandardNotUsable(
                        f"reference_standards[{i}]",
                        f"standard {row.id} ({row.name}, serial {row.serial}, certificate "
                        f"{row.certificate_number}) was due for calibration on {row.due_on}; it "
                        "cannot be used",
                    )
                if row.expanded_uncertainty_deg is None or row.coverage_factor is None:
                    raise StandardNotUsable(
                        f"reference_standards[{i}]",
                        f"standard {row.id} ({row.name}, serial {row.serial}, certificate "
                        f"{row.certificate_number}) states no numeric uncertainty (its text "
                        f"{row.uncertainty!r} does not read as an angle with its coverage "
                        "factor); register it again with expanded_uncertainty_deg and "
                        "coverage_factor",
                    )
                out.append(row)
        return out

    def notify_standards_due(
        self, *, today: dt.date, within_days: int, actor: str = "daemon"
    ) -> list[int]:
        """A `standard.due_soon` event, once per due date, for each standard due within
        `within_days`."""
        with self._db.transaction() as session:
            rows = list(
                session.scalars(
                    sa.select(ReferenceStandard).where(
                        ReferenceStandard.due_on <= today + dt.timedelta(days=within_days)
                    )
                )
            )
            sent: list[int] = []
            for row in rows:
                if row.due_soon_notified_on == row.due_on:
                    continue
                row.due_soon_notified_on = row.due_on
                self._db.audit(
                    session,
                    actor,
                    "standard.due_soon",
                    "reference_standard",
                    row.id,
                    {
                        "standard_id": row.id,
                        "name": row.name,
                        "serial": row.serial,
                        "certificate_number": row.certificate_number,
                        "due_on": row.due_on.isoformat(),
                        "days_left": (row.due_on - today).days,
                    },
                )
                sent.append(row.id)
            return sent
