"""What a sensor reads in the seconds after a stage move: the table's damped ringing, seen through
the sensor's own first-order response.

A move of Δ degrees at constant rate over T seconds leaves the table ringing about its new angle,
A·Δ·e^(−t/τ_d)·cos(2π f t) after the move ends (A: `ringing_amplitude_deg_per_deg`), and a sensor of
time constant τ that followed the ramp lags it by Δ·(τ/T)(1 − e^(−T/τ)) when the move ends (a step,
Δ, when T = 0). The sensor's output is the exact first-order response to that input:
    y(t) = Re[a·H·e^(st)] + (y0 − Re[a·H])·e^(−t/τ),  s = −1/τ_d + 2πf·i,  H = 1 / (1 + sτ),
the deviation from the settled reading. Moves superpose (the system is linear), so a reading at time
t carries the sum over the moves before it. Pure functions of the moves and the time: the daemon's
simulated instruments and `tiltlab simulate` call the same ones, so equal bench times give equal
readings.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.physics.effects import EffectSet

# the simulated controller's default velocity: offline runs replay moves at it
SIM_STAGE_VELOCITY_PPS = 4000
NEGLIGIBLE = 1e-9  # of a move's size: a move whose transient has decayed below this is forgotten


@dataclass(frozen=True)
class Settling:
    """The settling of a stage bench (scenario `effects.settling`); all zero: readings settle at
    once."""

    sensor_time_constant_s: float = 0.0
    ringing_amplitude_deg_per_deg: float = 0.0
    ringing_frequency_hz: float = 0.0
    ringing_decay_s: float = 0.0

    @property
    def is_instant(self) -> bool:
        return self.sensor_time_constant_s <= 0 and (
            self.ringing_amplitude_deg_per_deg <= 0 or self.ringing_decay_s <= 0
        )

    def lasts_s(self) -> float:
        """How long after a move its transient is still above NEGLIGIBLE of the move."""
        slowest = max(self.sensor_time_constant_s, self.ringing_decay_s, 0.0)
        return slowest * float(np.log(1.0 / NEGLIGIBLE))


def settling_of(fx: EffectSet) -> Settling:
    """A stage bench's settling from its effects (all zero when `settling` is not named)."""
    return Settling(
        *(
            fx.get("settling", param)
            for param in (
                "sensor_time_constant_s",
                "ringing_amplitude_deg_per_deg",
                "ringing_frequency_hz",
                "ringing_decay_s",
            )
        )
    )


@dataclass(frozen=True)
class Move:
    """One stage axis's move: it began at `t0_s` (bench seconds) and moved `delta_deg` in
    `duration_s`."""

    t0_s: float
    delta_deg: float
    duration_s: float

    @property
    def end_s(self) -> float:
        return self.t0_s + self.duration_s


def move_transient_deg(st: Settling, move: Move, t_s: ArrayLike) -> NDArray[np.float64]:
    """A sensor's reading minus its settled value at bench times `t_s`, from one move (zero before
    it began).

    While the move runs the sensor lags the ramp (its first-order response to it); after it ends the
    lag decays and the table's ringing, filtered by the sensor, adds to it.
    """
    t = np.atleast_1d(np.asarray(t_s, dtype=float))
    out = np.zeros_like(t)
    if st.is_instant or move.delta_deg == 0:
        return out
    tau, big_t, delta = st.sensor_time_constant_s, move.duration_s, move.delta_deg
    during = (t >= move.t0_s) & (t < move.end_s)
    if during.any() and tau > 0:
        rate = delta / big_t
        out[during] = -rate * tau * (1.0 - np.exp(-(t[during] - move.t0_s) / tau))
    after = t >= move.end_s
    if not after.any():
        return out
    dt = t[after] - move.end_s
    y0 = _lag_at_end_deg(tau, big_t, delta)
    forced, start = _filtered_ringing_deg(st, delta, dt)
    free = (y0 - start) * np.exp(-dt / tau) if tau > 0 else 0.0 * dt
    out[after] = forced + free
    return out


def settled_within_s(
    st: Settling, delta_deg: float, rate_deg_per_s: float, level_deg: float, step_s: float = 0.01
) -> float:
    """How long after a move of `delta_deg` at `rate_deg_per_s` ends its transient stays within
    `level_deg` for good (on a grid of `step_s`): the least settling any rule can give a stand whose
    readings must carry no more of it than that (a mean of one reading)."""
    return mean_settled_within_s(st, delta_deg, rate_deg_per_s, level_deg, 1, 0.0, step_s)


def mean_settled_within_s(
    st: Settling,
    delta_deg: float,
    rate_deg_per_s: float,
    level_deg: float,
    readings: int,
    interval_s: float,
    step_s: float = 0.01,
) -> float:
    """How long after a move of `delta_deg` at `rate_deg_per_s` ends the mean of `readings`
    readings `interval_s` apart, the first of them taken then, carries at most `level_deg` of the
    transient, and so does the mean of any set begun later: the least settling that keeps the
    transient out of a point's mean to that level. A point's mean of n readings has a standard
    error of σ/√n; a transient within one reading's noise σ at the first of them can still be
    several of those (a slow sensor's remnant decays over the readings but not to nothing)."""
    if st.is_instant or delta_deg == 0 or rate_deg_per_s <= 0 or readings < 1:
        return 0.0
    duration = abs(delta_deg) / rate_deg_per_s
    starts = np.arange(0.0, st.lasts_s() + step_s, step_s)
    t = starts[:, None] + interval_s * np.arange(readings)[None, :]
    transient = move_transient_deg(st, Move(-duration, delta_deg, duration), t.ravel())
    means = transient.reshape(t.shape).mean(axis=1)
    above = np.nonzero(np.abs(means) >= level_deg)[0]
    if not above.size:
        return 0.0
    return float(starts[min(above[-1] + 1, starts.size - 1)])


def _lag_at_end_deg(tau: float, big_t: float, delta: float) -> float:
    """y0 of the model: how far the sensor lags the ramp when the move ends (the whole step when
    the move is instant, nothing for an instant sensor)."""
    if tau <= 0:
        return 0.0
    if big_t <= 0:
        return -delta
    return float(-delta * (tau / big_t) * (1.0 - np.exp(-big_t / tau)))


def _filtered_ringing_deg(
    st: Settling, delta: float, dt: NDArray[np.float64]
) -> tuple[NDArray[np.float64], float]:
    """The forced part Re[a·H·e^(st)] at times `dt` after the move, and its value at the move's end,
    kept apart because the free part starts from that value."""
    tau = st.sensor_time_constant_s
    ringing_deg = st.ringing_amplitude_deg_per_deg * delta
    if ringing_deg != 0 and st.ringing_decay_s > 0:
        pole = complex(-1.0 / st.ringing_decay_s, 2.0 * np.pi * st.ringing_frequency_hz)
        sensor_gain = 1.0 / (1.0 + pole * tau)
        forced = np.real(ringing_deg * sensor_gain * np.exp(pole * dt))
        start = float(np.real(ringing_deg * sensor_gain))
        return forced, start
    return np.zeros_like(dt), 0.0


def transient_deg(st: Settling, moves: Iterable[Move], t_s: ArrayLike) -> NDArray[np.float64]:
    """The sum of the moves' transients at bench times `t_s` (the system is linear)."""
    t = np.atleast_1d(np.asarray(t_s, dtype=float))
    total = np.zeros_like(t)
    for m in moves:
        total += move_transient_deg(st, m, t)
    return total


def transient_along_deg(st: Settling, moves: Sequence[Move], t_s: ArrayLike) -> NDArray[np.float64]:
    """`transient_deg` at sorted times `t_s`, each move evaluated only while its transient lasts (a
    long offline run costs what its moves cost, not moves x rows)."""
    t = np.atleast_1d(np.asarray(t_s, dtype=float))
    total = np.zeros_like(t)
    if st.is_instant:
        return total
    horizon = st.lasts_s()
    for m in moves:
        lo, hi = np.searchsorted(t, [m.t0_s, m.end_s + horizon])
        if hi > lo:
            total[lo:hi] += move_transient_deg(st, m, t[lo:hi])
    return total


def moves_along(
    positions_deg: Sequence[float],
    start_deg: float,
    t_depart_s: Sequence[float],
    rate_deg_per_s: float,
) -> list[Move]:
    """The moves of a stage axis that visits `positions_deg` in turn from `start_deg`, leaving for
    each at `t_depart_s` and running at `rate_deg_per_s`: how an offline run is replayed."""
    moves, prev = [], start_deg
    for position, t in zip(positions_deg, t_depart_s):
        step_deg = float(position) - prev
        if step_deg != 0:
            moves.append(
                Move(
                    float(t),
                    step_deg,
                    abs(step_deg) / rate_deg_per_s if rate_deg_per_s > 0 else 0.0,
                )
            )
        prev = float(position)
    return moves


def recent(st: Settling, moves: list[Move], now_s: float) -> list[Move]:
    """The moves whose transient may still show at `now_s` (older ones forgotten)."""
    horizon = st.lasts_s()
    return [m for m in moves if now_s - m.end_s < horizon]


def step_response_fit(
    t_s: ArrayLike, reading_deg: ArrayLike, delta_deg: float, duration_s: float = 0.0
) -> Settling:
    """The settling a recorded step shows (readings after a move of `delta_deg` lasting
    `duration_s`, times from its end): time constant, ringing amplitude per degree, frequency and
    decay fitted by least squares to the model above. Used to check the simulator against the
    scenario."""
    from scipy.optimize import least_squares

    t = np.asarray(t_s, dtype=float)
    y = np.asarray(reading_deg, dtype=float)
    settled = float(np.median(y[t > t.max() * 0.8]))
    dev = y - settled

    def model(p: NDArray[np.float64]) -> NDArray[np.float64]:
        st = Settling(abs(p[0]), p[1], abs(p[2]), abs(p[3]))
        return move_transient_deg(st, Move(-duration_s, delta_deg, duration_s), t)

    # the lag alone first, then the ringing's frequency from the spectrum of what the lag leaves,
    # then all four
    lag = min(
        (
            least_squares(lambda p: model(np.array([p[0], 0.0, 1.0, 1.0])) - dev, [tau0])
            for tau0 in (0.05, 0.5, 3.0)
        ),
        key=lambda r: r.cost,
    )
    rest = dev - model(np.array([lag.x[0], 0.0, 1.0, 1.0]))
    spectrum = np.abs(np.fft.rfft(rest - rest.mean()))
    freqs = np.fft.rfftfreq(t.size, float(np.median(np.diff(t))))
    f0 = float(freqs[1:][np.argmax(spectrum[1:])]) if t.size > 4 else 1.0
    amp0 = float(np.max(np.abs(rest))) / max(abs(delta_deg), 1e-12)
    best = None
    for decay0 in (0.2, 1.0):
        for sign in (1.0, -1.0):
            fit = least_squares(lambda p: model(p) - dev, [abs(lag.x[0]), sign * amp0, f0, decay0])
            if best is None or fit.cost < best.cost:
                best = fit
    assert best is not None
    params = best.x
    return Settling(abs(params[0]), float(params[1]), abs(params[2]), abs(params[3]))
