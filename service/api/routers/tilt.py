"""GET /tilt: the corrected table tilt from the latest reading, never waiting for a stage move."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, NamedTuple

from fastapi import APIRouter, Query
from fastapi.responses import Response

from service.api.auth import Reader
from service.api.deps import BenchQuery, JobsDep
from service.api.models.problem import READ, problem_responses
from service.api.models.tilt import Tilt
from service.bench.corrected import (
    CorrectedTilt,
    averaged_at_stand,
    calibrated_range_note,
    calibration_json,
    corrected_reading,
    in_calibrated_range,
    reference_tilt,
    sensor_temp_c,
    stale_after_s,
)
from service.bench.runtime import BenchRuntime
from service.instruments.base import Reading
from service.jobs.manager import JobManager

router = APIRouter(tags=["tilt"])
MAX_AVERAGE_S = 600.0  # the longest averaging window asked for (bench seconds)


def _pair(r: Any) -> dict[str, float] | None:
    return None if r is None else {"x_deg": r.x_deg, "y_deg": r.y_deg}


AverageQuery = Annotated[
    float | None,
    Query(
        gt=0,
        le=MAX_AVERAGE_S,
        description="serve the mean of the corrected readings of the last average_s seconds "
        "(bench seconds: the simulated clock's on a simulated bench) during which the stage "
        "stood still, with the uncertainty of that mean; table_tilt then carries n_readings and "
        "window_s",
    ),
]


@router.get("/tilt", response_model=Tilt, responses=problem_responses(*READ, 404))
async def tilt(
    bench: BenchQuery, jobs: JobsDep, _: Reader, average_s: AverageQuery = None
) -> Response:
    """Table tilt: the measurement sensor's latest reading through the active record, in the
    reference sensor's frame, with its expanded uncertainty (GUM, 95 %; coverage factors k, k_y from
    the effective degrees of freedom) from the record's covariance; null with
    the reason in `note` when no record is active (or the active one was withdrawn or refused) or
    the sensor is not answering. `in_calibrated_range` says whether the corrected tilt lies within
    the table tilts the record was fitted on; outside them it is still served, and `note` says so.
    When the active record models the reference sensor's own errors, `reference_tilt` is its latest
    reading through that model (`raw` keeps the reading as it came). `stale` is true
    when the latest reading is older than three output intervals plus 0.25 s.

    With `average_s`, `table_tilt` is the mean of the readings since the later of (the latest
    reading's time − average_s) and the moment the readings settled after the stage's last move (the
    statistical settling test against one reading's noise, as a job settles its points), `window_s`
    says how long that is and `n_readings` how many; its uncertainty is that of the mean (the
    readings' Type A, their correlation allowed for, combined with the parts that do not average
    down). While the stage moves or the readings have not settled, or with fewer than two readings,
    it is null and `note` says why."""
    return Response(tilt_answer(bench, jobs, average_s), media_type="application/json")


def tilt_answer(bench: BenchRuntime, jobs: JobManager, average_s: float | None = None) -> bytes:
    """The body of `GET /tilt` for one bench, as JSON (the route's and the prepared path's one
    source)."""
    now = dt.datetime.now(dt.UTC)
    meas = bench.latest("measurement_sensor")
    ref = bench.latest("reference_sensor")
    active = jobs.active.get(bench.name)
    age_s = stale = None
    notes: list[str] = []
    table: CorrectedTilt | None = None
    in_range = None
    if bench.kind != "stage":
        notes.append(
            f"{bench.name} is a {bench.kind} bench: table tilt is served for stage benches"
        )
    elif meas is None:
        st = bench.devices["measurement_sensor"].status
        notes.append(f"no reading from measurement_sensor on {st.port} ({st.state})")
    else:
        meas, table, age_s, stale, in_range = _stage_tilt(
            bench, jobs, active, meas, now, average_s, notes
        )
    pose = bench.pose
    body = Tilt.model_validate(
        {
            "bench": bench.name,
            "time_utc": meas.time_utc if meas else now,
            "age_s": age_s,
            "stale": stale,
            "table_tilt": table,
            "raw": {"measurement_sensor": _pair(meas), "reference_sensor": _pair(ref)},
            "reference_tilt": reference_tilt(active, ref, sensor_temp_c(meas, ref))
            if bench.kind == "stage"
            else None,
            "temp_c": sensor_temp_c(meas, ref),
            "stage": {"x_deg": pose.x_deg, "y_deg": pose.y_deg, "moving": pose.moving}
            if bench.kind == "stage"
            else None,
            "calibration": calibration_json(active),
            "in_calibrated_range": in_range,
            "note": "; ".join(notes),
        }
    )
    # serialised here, once, by the model's own serialiser (the route's response model documents it)
    return body.model_dump_json().encode()


class _StageTilt(NamedTuple):
    """What a stage bench's latest reading gives `GET /tilt`."""

    meas: Reading  # the reading served (the correction may pick the one before the latest)
    table: CorrectedTilt | None  # the corrected (or averaged) table tilt
    age_s: float
    stale: bool
    in_range: bool | None  # whether `table` lies in the calibrated range


def _stage_tilt(
    bench: BenchRuntime,
    jobs: JobManager,
    active: Any,
    meas: Reading,
    now: dt.datetime,
    average_s: float | None,
    notes: list[str],
) -> _StageTilt:
    """The latest reading's age and its table tilt through the active record, when there is one
    and the reading is fresh; what stands in the way is said in `notes`."""
    table: CorrectedTilt | None = None
    in_range = None
    if active is not None and average_s is None:
        # computed before the age: it may pick the one before
        meas, table = corrected_reading(bench, active, meas)
    age_s = max(0.0, (now - meas.time_utc).total_seconds())
    limit = stale_after_s(bench, "measurement_sensor")
    stale = age_s > limit
    if stale:
        st = bench.devices["measurement_sensor"].status
        notes.append(
            f"measurement_sensor on {st.port} has sent nothing for {age_s:.2f} s ({st.state})"
        )
    if active is None:
        why = jobs.inactive_notes.get(bench.name)
        notes.append(
            "no active calibration record: raw readings only (POST /records/{id}/activate)"
            + (f"; {why}" if why else "")
        )
    elif stale:
        table = None
    else:
        table, in_range = _corrected(bench, active, meas, table, average_s, notes)
    return _StageTilt(meas, table, age_s, stale, in_range)


def _corrected(
    bench: BenchRuntime,
    active: Any,
    meas: Reading,
    table: CorrectedTilt | None,
    average_s: float | None,
    notes: list[str],
) -> tuple[CorrectedTilt | None, bool | None]:
    """The table tilt through the active record (averaged when asked) and whether it lies in the
    calibrated range; the record it went through, and a tilt outside that range, said in
    `notes`."""
    if average_s is not None:
        table, said = averaged_at_stand(bench, active, meas, average_s)
        notes.append(said)
    notes.append(
        f"corrected through record {active.record_id} v{active.version} "
        f"({active.method_name}, {active.status})"
    )
    in_range = in_calibrated_range(active, table) if table is not None else None
    if in_range is False and table is not None:
        notes.append(calibrated_range_note(active, table))
    return table, in_range
