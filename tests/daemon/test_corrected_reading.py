"""Which reading `GET /tilt` corrects: the latest on a bench at its own pace; on a bench sped up
past one reading per few milliseconds of real time, at most one a few milliseconds (each costs a
correction)."""

from __future__ import annotations

import datetime as dt
from typing import Any

import pytest

import service.bench.corrected as corrected
from service.bench.corrected import MIN_CORRECTION_GAP_S, corrected_reading
from service.clock import Clock
from service.instruments.base import Reading

INTERVAL_S = 0.02  # bench seconds between readings: a 50 Hz sensor


class Bench:
    def __init__(self, speed: float) -> None:
        self.clock = Clock(speed)

    def output_interval_s(self, role: str) -> float:
        return INTERVAL_S


def reading(bench_s: float, x_deg: float) -> Reading:
    return Reading(
        role="measurement_sensor",
        bench_s=bench_s,
        time_utc=dt.datetime.now(dt.UTC),
        x_deg=x_deg,
        y_deg=0.0,
    )


@pytest.fixture
def corrections(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    made: list[float] = []

    def correct(active: Any, meas: Reading) -> dict[str, Any]:
        made.append(meas.bench_s)
        return {"x_deg": meas.x_deg}

    monkeypatch.setattr(corrected, "corrected_tilt", correct)
    return made


@pytest.mark.parametrize("speed", [1.0, 4.0])
def test_a_bench_at_its_own_pace_has_every_latest_reading_corrected(
    corrections: list[float], speed: float
) -> None:
    bench, active = Bench(speed), object()
    assert Clock(speed).real_seconds(INTERVAL_S) >= MIN_CORRECTION_GAP_S
    for i in range(5):
        meas = reading(i * INTERVAL_S, float(i))
        served, table = corrected_reading(bench, active, meas)  # type: ignore[arg-type]
        assert served is meas and table == {"x_deg": float(i)}
    assert len(corrections) == 5


def test_a_sped_up_bench_has_at_most_one_reading_corrected_per_gap(
    corrections: list[float],
) -> None:
    bench, active = Bench(20.0), object()
    gap_bench_s = bench.clock.bench_seconds(MIN_CORRECTION_GAP_S)
    # a reading every real millisecond
    readings = [reading(i * INTERVAL_S, float(i)) for i in range(40)]
    served = [corrected_reading(bench, active, r) for r in readings]  # type: ignore[arg-type]
    for (meas, table), latest in zip(served, readings, strict=True):
        assert table == {"x_deg": meas.x_deg}  # the tilt served is always its own reading's
        assert 0.0 <= latest.bench_s - meas.bench_s < gap_bench_s  # never older than one gap
    # one per 4 readings of 1 ms
    assert corrections == sorted(set(corrections)) and len(corrections) == 10
    assert all(
        b - a >= gap_bench_s * 0.999 for a, b in zip(corrections, corrections[1:], strict=False)
    )
    other = object()  # a newly active record: corrected at once
    meas, _ = corrected_reading(bench, other, readings[-1])  # type: ignore[arg-type]
    assert meas is readings[-1] and corrections[-1] == readings[-1].bench_s
