"""The active calibration of a bench's measurement sensor: what GET /tilt corrects with and
levelling aims by."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from service.bench.runtime import BenchRuntime
from service.calibration.budget import UncertaintyBudget
from service.calibration.methods.stage.base import noise_state
from service.calibration.methods.stage.reference import ReferenceErrors, reference_errors
from service.calibration.model import CalibrationModel, stored_table_tilt_range, table_tilt_range
from service.calibration.reading_noise import ReadingNoise, pooled_reading_noise
from service.calibration.registry import Method, get_method
from service.jobs.state import DAEMON
from service.storage.errors import ConflictError, UnknownEntity
from service.storage.models import CalibrationRecord
from service.storage.store import ApprovalsRepo, RecordsRepo

log = logging.getLogger("tiltlab.jobs")


@dataclass(frozen=True)
class ActiveModel:
    record_id: int
    version: int
    method_name: str
    model: CalibrationModel
    method: Method
    # the record's uncertainty budget (what adds to the fit's part)
    budget: UncertaintyBudget | None = None
    status: str = "draft"  # draft | approved (a rejected record is never loaded)
    # the table tilts (reference sensor's frame) the record was fitted on: {"x": [min, max], "y":
    # [min, max]}
    table_tilt_range_deg: dict[str, list[float]] | None = None
    # what the record knows of the reference sensor's own reading errors (None: its readings are the
    # table tilt)
    reference: ReferenceErrors | None = None
    # the measurement sensor's single-reading noise from the readings the record's job stored (None:
    # no stored readings; the fit's residual, of one reading per point, stands for it)
    reading_noise: ReadingNoise | None = None

    @cached_property
    def live_model(self) -> CalibrationModel:
        """The model a live reading is corrected with: the record's, its reading-noise term that of
        ONE reading (the fit's residual is of point means where points averaged several
        readings)."""
        if self.reading_noise is None:
            return self.model
        return replace(self.model, state={**self.model.state, **noise_state(self.reading_noise)})

    @cached_property
    def parameter_model(self) -> CalibrationModel:
        """The model with no reading noise: a corrected value's uncertainty from the parameters
        alone, the part that does not average down over many readings (an averaged tilt adds its
        readings' Type A to it)."""
        return replace(
            self.live_model,
            state={
                **self.live_model.state,
                **noise_state(ReadingNoise(0.0, float("inf"), "none (parameters only)")),
            },
        )

    @property
    def reading_noise_source(self) -> str:
        """Which estimate of one reading's noise the served uncertainty uses."""
        if self.reading_noise is not None:
            return self.reading_noise.source
        return (
            "the residual of the record's fit (no readings stored with the record: each of its "
            "points is taken as one reading)"
        )


PointSpreads = Callable[[int, int], list[tuple[int, float | None, float | None]]]


def load_active(
    records: RecordsRepo,
    approvals: ApprovalsRepo,
    bench: BenchRuntime,
    fit_columns: Callable[[int, int], dict[str, NDArray[np.float64]]],
    point_spreads: PointSpreads | None = None,
) -> tuple[ActiveModel | None, str | None]:
    """Blocking (database): the bench's active stage record, checked before use, and why there is
    none. A record whose stored content no longer matches its hash is refused (the bench stays
    uncorrected), and a rejected one is withdrawn."""
    dev = bench.device_ids.get("measurement_sensor")
    rec = records.active_record(dev, "stage") if dev is not None else None
    if rec is None:
        return None, records.inactive_reason(dev, "stage") if dev is not None else None
    if (why := records.unusable_reason(rec.id)) is not None:
        note = f"the active record is refused: {why}"
        log.warning("bench %s: %s", bench.name, note)
        if approvals.record_status(rec.id) == "rejected" and dev is not None:
            with contextlib.suppress(ConflictError):  # a rejected record is never used: withdraw it
                records.deactivate(
                    dev,
                    "stage",
                    actor=DAEMON,
                    replaces=rec.id,
                    reason=f"{why}; a rejected record is never used",
                )
        return None, note
    model = CalibrationModel.from_json_dict(rec.model, f"record {rec.id}")
    return ActiveModel(
        rec.id,
        rec.version,
        rec.method,
        model,
        get_method("stage", rec.method),
        (rec.raw_data or {}).get("budget"),
        status=approvals.record_status(rec.id),
        table_tilt_range_deg=table_tilt_range_of(rec, fit_columns, model),
        reference=reference_errors(model),
        reading_noise=reading_noise_of(rec, point_spreads),
    ), None


def reading_noise_of(
    rec: CalibrationRecord, point_spreads: PointSpreads | None
) -> ReadingNoise | None:
    """The measurement sensor's single-reading noise pooled over the points its job stored (None
    without them)."""
    if point_spreads is None or rec.job_id is None or rec.device_id is None:
        return None
    with contextlib.suppress(UnknownEntity):
        return pooled_reading_noise(point_spreads(rec.job_id, rec.device_id))
    return None


def table_tilt_range_of(
    rec: CalibrationRecord,
    fit_columns: Callable[[int, int], dict[str, NDArray[np.float64]]],
    model: CalibrationModel | None = None,
) -> dict[str, list[float]] | None:
    """The table tilts a stage record was fitted on: from its model, else (records made before
    models kept it) from the settled points its job fitted; None for other kinds or without
    either."""
    if rec.kind != "stage":
        return None
    model = model or CalibrationModel.from_json_dict(rec.model, f"record {rec.id}")
    seen = stored_table_tilt_range(model)
    if seen is None and rec.job_id is not None:
        with contextlib.suppress(UnknownEntity, KeyError):
            seen = table_tilt_range(
                fit_columns(rec.job_id, int((rec.raw_data or {}).get("fit_points", 10**9)))
            )
    return seen
