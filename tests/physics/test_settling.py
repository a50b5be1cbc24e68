"""The simulated settling after a move is what the scenario says: a step recorded from the simulated
bench gives back the scenario's time constant and ringing, and an offline run sees the same
transient."""

from __future__ import annotations

import numpy as np
import pytest

from service.clock import Clock
from service.instruments.sim.world import StageWorld
from service.physics.settling import (
    Move,
    Settling,
    mean_settled_within_s,
    move_transient_deg,
    moves_along,
    settled_within_s,
    step_response_fit,
    transient_along_deg,
)
from service.scenarios.model import StageScenario, load_scenario, parse_scenario


class HandClock(Clock):
    """A bench clock that moves only when the test moves it."""

    def __init__(self) -> None:
        super().__init__(1.0)
        self.now = 0.0

    def monotonic(self) -> float:
        return self.now


def _scenario(settling: dict[str, float], seed: int) -> StageScenario:
    data = load_scenario("seed000").model_dump(mode="json")
    data["effects"]["settling"] = settling
    data["seed"] = seed
    # stage repeatability is a constant offset over a step recorded at one pose: left out here
    data["effects"]["noise"]["stage_sigma_deg"] = 0.0
    sc = parse_scenario(data)
    assert isinstance(sc, StageScenario)
    return sc


def _record_step(sc: StageScenario, delta_deg: float, rate_hz: float = 100.0, span_s: float = 6.0):
    """Move the upper stage by `delta_deg` and record the measurement sensor's x reading after the
    move ends."""
    clock = HandClock()
    world = StageWorld(sc, clock)
    axis = world.axes[1]
    target = round(delta_deg / axis.pulse_deg)
    assert axis.move_to(target) == 0
    duration = abs(target) / axis.velocity_pps
    t_end = duration
    times = t_end + np.arange(0.0, span_s, 1.0 / rate_hz)
    xs = []
    for t in times:
        clock.now = float(t)
        xs.append(world.reading_deg("meas", float(t))[0])
    return times - t_end, np.array(xs), target * axis.pulse_deg, duration


SEED000 = {
    "sensor_time_constant_s": 0.3,
    "ringing_amplitude_deg_per_deg": 0.002,
    "ringing_frequency_hz": 4.0,
    "ringing_decay_s": 0.5,
}
FAST_SENSOR = {
    "sensor_time_constant_s": 0.1,
    "ringing_amplitude_deg_per_deg": 0.004,
    "ringing_frequency_hz": 3.0,
    "ringing_decay_s": 0.8,
}
CASES = [SEED000, FAST_SENSOR]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_time_constant_and_ringing_recovered_from_a_recorded_step(seed):
    """A 3 deg step read at 100 Hz for 6 s through reading noise of 0.001 deg; with a fast sensor
    (0.1 s) the table's ringing reaches the reading (about 0.004 deg) and all four parameters come
    back."""
    sc = _scenario(FAST_SENSOR, seed)
    t, x, delta, duration = _record_step(sc, 3.0)
    fit = step_response_fit(t, x, delta, duration)
    assert fit.sensor_time_constant_s == pytest.approx(
        FAST_SENSOR["sensor_time_constant_s"], rel=0.05
    )
    assert fit.ringing_frequency_hz == pytest.approx(FAST_SENSOR["ringing_frequency_hz"], rel=0.05)
    assert fit.ringing_decay_s == pytest.approx(FAST_SENSOR["ringing_decay_s"], rel=0.3)
    assert fit.ringing_amplitude_deg_per_deg == pytest.approx(
        FAST_SENSOR["ringing_amplitude_deg_per_deg"], rel=0.3
    )


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_seed000_settling_recovered_time_constant_and_ringing_hidden_below_noise(seed):
    """The seed 000 defaults: the 0.3 s sensor filters the table's 4 Hz ringing to under 0.0007 deg,
    below the reading noise, so a recorded step shows the time constant; the fitted model still
    matches the truth's transient within three times the noise."""
    sc = _scenario(SEED000, seed)
    t, x, delta, duration = _record_step(sc, 3.0)
    fit = step_response_fit(t, x, delta, duration)
    assert fit.sensor_time_constant_s == pytest.approx(SEED000["sensor_time_constant_s"], rel=0.05)
    move = Move(-duration, delta, duration)
    gap = move_transient_deg(fit, move, t) - move_transient_deg(Settling(**SEED000), move, t)
    # three times the reading noise, over a transient starting at 0.8 deg
    assert np.max(np.abs(gap)) < 0.003


def test_the_seed000_preset_states_its_settling():
    sc = load_scenario("seed000")
    assert sc.effects.settling is not None and sc.effects.settling.model_dump() == SEED000


def test_a_bench_without_settling_reads_the_new_pose_at_once():
    sc = _scenario({}, 3)
    t, x, _, _ = _record_step(sc, 3.0, span_s=1.0)
    # nothing but reading noise (sigma 0.001 deg) from the first reading on
    assert np.std(x) < 0.003 and abs(x[0] - np.mean(x)) < 0.005


def test_first_order_lag_and_step_limits():
    st = Settling(sensor_time_constant_s=1.0)
    # an instantaneous step: the sensor is Δ behind at once, e^-1 of it one time constant later
    y = move_transient_deg(st, Move(0.0, 2.0, 0.0), [0.0, 1.0, 3.0])
    assert y == pytest.approx([-2.0, -2.0 * np.exp(-1), -2.0 * np.exp(-3)])
    # a slow ramp: the lag at its end is rate x tau (1 - e^-T/tau)
    y = move_transient_deg(st, Move(0.0, 10.0, 10.0), [10.0])
    assert y[0] == pytest.approx(-1.0 * (1 - np.exp(-10.0)))
    # ringing alone (no sensor lag): the table's own damped cosine
    st = Settling(ringing_amplitude_deg_per_deg=0.01, ringing_frequency_hz=2.0, ringing_decay_s=0.5)
    t = np.linspace(0, 2, 9)
    assert move_transient_deg(st, Move(0.0, 3.0, 0.0), t) == pytest.approx(
        0.03 * np.exp(-t / 0.5) * np.cos(2 * np.pi * 2.0 * t)
    )


def test_offline_run_sees_the_transient_the_simulated_bench_shows():
    sc = _scenario(SEED000, 4)
    clock = HandClock()
    world = StageWorld(sc, clock)
    axis = world.axes[1]
    reads = []
    depart = []
    for target_deg in (3.0, -1.5, 0.75):
        target = round(target_deg / axis.pulse_deg)
        start = clock.now
        depart.append(start)
        assert axis.move_to(target) == 0
        clock.now = start + abs(target - axis._start) / axis.velocity_pps
        for dt in (0.0, 0.2, 0.9):
            reads.append(clock.now + dt)
        clock.now += 1.0
    got = world._settling_deg(np.array(reads) - world.t0)[0]
    positions = [round(p / axis.pulse_deg) * axis.pulse_deg for p in (3.0, -1.5, 0.75)]
    moves = moves_along(positions, 0.0, depart, axis.velocity_pps * axis.pulse_deg)
    assert transient_along_deg(world.settling, moves, reads) == pytest.approx(got, abs=1e-12)


@pytest.mark.parametrize("tau", [0.3, 1.5])
@pytest.mark.parametrize("delta", [-9.0, 0.5, 12.0])
def test_settled_within_is_the_first_order_lag_decaying_to_the_level(tau, delta):
    """Without ringing the sensor lags a ramp at `rate` by y0 = δ (τ/T)(1 − e^(−T/τ)) when the move
    ends (T = |δ|/rate) and the lag decays as e^(−t/τ): it stays within `level` after
    τ ln(|y0| / level)."""
    rate, level = 2.0, 0.001
    duration = abs(delta) / rate
    lag = abs(delta) * tau / duration * (1.0 - np.exp(-duration / tau))
    expected = tau * np.log(lag / level)
    st = Settling(tau, 0.0, 0.0, 0.0)
    assert settled_within_s(st, delta, rate, level, step_s=0.001) == pytest.approx(
        expected, abs=0.002
    )
    # a level above the whole lag is held at once, a bench without settling at once
    assert settled_within_s(st, delta, rate, 1.1 * lag) == 0.0
    assert settled_within_s(Settling(), delta, rate, level) == 0.0


def test_settled_within_waits_out_the_ringing_too():
    """The table's ringing (0.002 deg/deg, decaying over 0.5 s) after a 9 deg move, through a
    0.05 s sensor, starts near 0.018 deg: within 0.001 deg it takes about 0.5 ln(18) = 1.4 s, well
    past the sensor's own lag (0.05 ln(0.1 / 0.001) = 0.23 s)."""
    ringing = Settling(0.05, 0.002, 4.0, 0.5)
    waited = settled_within_s(ringing, 9.0, 2.0, 0.001, step_s=0.001)
    assert 1.0 < waited <= 0.5 * np.log(0.018 / 0.001) + 0.01
    assert waited > settled_within_s(Settling(0.05, 0.0, 0.0, 0.0), 9.0, 2.0, 0.001) + 0.8


@pytest.mark.parametrize("tau", [0.3, 1.5])
@pytest.mark.parametrize("readings", [1, 30, 118])
def test_mean_settled_within_is_the_decaying_lag_averaged_over_the_readings(tau, readings):
    """Readings dt apart from w after the move carry y0 e^(−w/τ) e^(−k dt/τ): their mean is
    y0 e^(−w/τ) S / n, S = (1 − e^(−n dt/τ)) / (1 − e^(−dt/τ)), within `level` from
    w = τ ln(|y0| S / (n level)). One reading is settled_within_s."""
    delta, rate, dt, level = 8.0, 2.8, 0.04, 0.0003
    duration = delta / rate
    lag = delta * tau / duration * (1.0 - np.exp(-duration / tau))
    s = (1.0 - np.exp(-readings * dt / tau)) / (1.0 - np.exp(-dt / tau))
    expected = tau * np.log(lag * s / (readings * level))
    st = Settling(tau, 0.0, 0.0, 0.0)
    waited = mean_settled_within_s(st, delta, rate, level, readings, dt, step_s=0.001)
    assert waited == pytest.approx(expected, abs=0.002)
    if readings == 1:
        assert waited == pytest.approx(settled_within_s(st, delta, rate, level, step_s=0.001))
    assert mean_settled_within_s(Settling(), delta, rate, level, readings, dt) == 0.0


def test_a_slow_sensor_settled_to_one_reading_s_noise_still_biases_a_long_mean():
    """The floor's level (the transient within one reading's noise σ) leaves a slow sensor's
    remnant in a point's mean of many readings: keeping it within half the mean's standard error,
    σ/(2√n), takes longer; for a fast sensor the difference is a fraction of a second."""
    sigma, n, dt = 0.0012, 118, 0.04
    slow, fast = Settling(1.5, 0.002, 2.5, 1.0), Settling(0.3, 0.002, 4.0, 0.5)
    for st, longer_s in ((slow, (2.5, 4.0)), (fast, (0.05, 1.0))):
        per_reading = settled_within_s(st, 8.0, 2.8, sigma)
        in_mean = mean_settled_within_s(st, 8.0, 2.8, 0.5 * sigma / np.sqrt(n), n, dt)
        assert per_reading + longer_s[0] < in_mean < per_reading + longer_s[1]
