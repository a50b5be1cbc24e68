"""Diagnoses of stored records: asked for once, ended once (both rows append-only).

A diagnosis without a result is queued or running in the daemon that accepted it; one the
daemon lost by a restart is ended as failed when the daemon starts again.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterable, Mapping
from typing import cast

import sqlalchemy as sa
from sqlalchemy.orm import defer

from service.storage.errors import ConflictError
from service.storage.models import CalibrationRecord, Diagnosis, DiagnosisResult, utc_now
from service.storage.store.checks import require_doc, require_text
from service.storage.store.database import Database
from service.storage.store.lookups import row_in

INTERRUPTED_DIAGNOSIS = "interrupted: the daemon stopped while the diagnosis ran; start it again"


class DiagnosesRepo:
    def __init__(self, db: Database) -> None:
        self._db = db

    def create_diagnosis(
        self, record_id: int, *, sensor: str, baseline: str, actor: str
    ) -> Diagnosis:
        with self._db.transaction() as session:
            row_in(session, CalibrationRecord, record_id, "record")
            diagnosis = Diagnosis(
                record_id=record_id,
                sensor=require_text("sensor", sensor, 8),
                baseline=require_text("baseline", baseline, 20),
                created_by=require_text("actor", actor),
                created_at=utc_now(),
            )
            session.add(diagnosis)
            session.flush()
            self._db.audit(
                session,
                actor,
                "diagnosis.create",
                "diagnosis",
                diagnosis.id,
                {"record_id": record_id, "sensor": sensor, "baseline": baseline},
            )
            return diagnosis

    def finish_diagnosis(
        self,
        diagnosis_id: int,
        *,
        state: str,
        started_at: dt.datetime | None,
        summary: Mapping[str, object],
        report_html: str | None,
        error: str | None,
        actor: str,
    ) -> DiagnosisResult:
        """The one result of a diagnosis; its event `diagnosis.finished` goes to the feed and
        webhooks."""
        with self._db.transaction() as session:
            row = row_in(session, Diagnosis, diagnosis_id, "diagnosis")
            if (
                session.scalar(
                    sa.select(DiagnosisResult.id).where(
                        DiagnosisResult.diagnosis_id == diagnosis_id
                    )
                )
                is not None
            ):
                raise ConflictError(f"diagnosis {diagnosis_id} has already ended")
            result = DiagnosisResult(
                diagnosis_id=diagnosis_id,
                state=state,
                started_at=started_at,
                finished_at=utc_now(),
                summary=require_doc("summary", summary),
                report_html=report_html,
                error=error,
            )
            session.add(result)
            session.flush()
            self._db.audit(
                session,
                actor,
                "diagnosis.finish",
                "diagnosis",
                diagnosis_id,
                {
                    "diagnosis_id": diagnosis_id,
                    "record_id": row.record_id,
                    "state": state,
                    # the workflow's summary lists the effects it named
                    "named_effects": list(
                        cast("Iterable[object]", summary.get("named_effects", []))
                    ),
                    "error": error,
                },
            )
            return result

    def get_diagnosis(self, diagnosis_id: int) -> tuple[Diagnosis, DiagnosisResult | None]:
        with self._db.session() as session:
            row = row_in(session, Diagnosis, diagnosis_id, "diagnosis")
            result = session.scalar(
                sa.select(DiagnosisResult).where(DiagnosisResult.diagnosis_id == diagnosis_id)
            )
            return row, result

    def list_diagnoses(
        self, record_id: int | None = None, *, before_id: int | None = None, limit: int = 100
    ) -> list[tuple[Diagnosis, DiagnosisResult | None]]:
        """Newest first, of one record or of all, from before `before_id` (the cursor); without the
        report pages (the largest part of a result, which a list does not show)."""
        with self._db.session() as session:
            stmt = (
                sa.select(Diagnosis, DiagnosisResult)
                .outerjoin(DiagnosisResult, DiagnosisResult.diagnosis_id == Diagnosis.id)
                .options(defer(DiagnosisResult.report_html, raiseload=True))
                .order_by(Diagnosis.id.desc())
                .limit(limit)
            )
            if record_id is not None:
                stmt = stmt.where(Diagnosis.record_id == record_id)
            if before_id is not None:
                stmt = stmt.where(Diagnosis.id < before_id)
            return [(diagnosis, result) for diagnosis, result in session.execute(stmt).all()]

    def unfinished_diagnoses(self) -> list[int]:
        with self._db.session() as session:
            stmt = (
                sa.select(Diagnosis.id)
                .outerjoin(DiagnosisResult, DiagnosisResult.diagnosis_id == Diagnosis.id)
                .where(DiagnosisResult.id.is_(None))
            )
            return list(session.scalars(stmt))

    def mark_diagnoses_interrupted(self, *, actor: str) -> list[int]:
        """At start-up: diagnoses a previous run left without a result end as failed."""
        ids = self.unfinished_diagnoses()
        for i in ids:
            self.finish_diagnosis(
                i,
                state="failed",
                started_at=None,
                summary={},
                report_html=None,
                error=INTERRUPTED_DIAGNOSIS,
                actor=actor,
            )
        return ids
