"""The simulated physical truth behind the simulated firmware: stage axes that move in bench
time, and the scenario's physics read at the present pose.

Everything is computed on demand from the bench clock, so a move at 4000 pulses/s takes the
same bench time at any speed factor, and several firmware threads see one consistent world.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict

import numpy as np

from service.clock import Clock
from service.errors import InputError
from service.instruments import controller as ctl
from service.physics.analog import ARCSEC_PER_RAD, AnalogSensor, simulate_scale
from service.physics.effects import EffectSet
from service.physics.rotation_axis import simulate_rotation
from service.physics.settling import Move, recent, settling_of, transient_deg
from service.physics.stage import StageGeometry, simulate_stage
from service.physics.turntable import TurntableInclinometer, turntable_readings
from service.scenarios.model import (
    RotationScenario,
    ScaleScenario,
    StageScenario,
    TurntableScenario,
    load_scenario,
)
from service.scenarios.run import effect_set, hardware_of, temperature

NO_LIMIT = 2_147_483_647

# A sensor at rest outputs a batch of readings computed at once (vectorised over the samples
# of its coming output intervals): the physics costs about the same for 1 point as for 32.
READINGS_PER_BATCH = 32
# positioning errors remembered (a move's intermediate poses each count as a stand)
STANDS_KEPT = 64


class _Batch:
    """One sensor's coming readings at one pose: bench times and (x, y) per sample."""

    def __init__(self, pose: tuple[object, ...], t_s: np.ndarray, x: np.ndarray, y: np.ndarray):
        self.pose = pose
        self.t_s = t_s
        self.xy = list(zip(x.tolist(), y.tolist()))
        self.next = 0


class Axis:
    """One controller axis: position in pulses, moving at the set velocity on the bench clock."""

    def __init__(
        self,
        clock: Clock,
        pulse_deg: float,
        velocity_pps: float,
        soft: tuple[int, int] | None,
        hard: tuple[int, int] | None,
    ) -> None:
        self.clock = clock
        self.pulse_deg = pulse_deg
        self.velocity_pps = float(velocity_pps)
        self.soft = soft
        self.hard = hard
        self.homed = True
        self.error = ctl.ERR_NONE
        self.direction = 1.0  # sign of the last move: the side backlash is taken up on
        self.moves = 0  # moves started: a stand of the stage is a pose between two of them
        self._pos = 0.0
        self._target = 0.0
        self._t0 = 0.0
        self._start = 0.0
        self._mode = ctl.STATE_READY
        self._lock = threading.RLock()
        # recent moves (bench clock times): the settling transient follows them
        self.recent_moves: list[Move] = []

    def _update(self) -> None:
        if self._mode not in (ctl.STATE_MOVING, ctl.STATE_HOMING):
            return
        t = self.clock.monotonic()
        span = self._target - self._start
        done = min(self.velocity_pps * (t - self._t0), abs(span))
        reached = self._start + math.copysign(done, span)
        if self.hard is not None and not self.hard[0] <= reached <= self.hard[1]:
            self._pos = float(min(max(reached, self.hard[0]), self.hard[1]))
            self._mode, self.error = ctl.STATE_HARD_LIMIT, ctl.ERR_HARD_LIMIT
            return
        self._pos = reached
        if done >= abs(span):
            self._pos = self._target
            if self._mode == ctl.STATE_HOMING:
                self.homed = True
            self._mode = ctl.STATE_READY

    @property
    def position(self) -> float:
        with self._lock:
            self._update()
            return self._pos

    @property
    def state(self) -> int:
        with self._lock:
            self._update()
            return self._mode

    def position_pulses(self) -> int:
        return int(round(self.position))

    def _go(self, target: float, mode: int) -> None:
        self._start, self._target, self._t0, self._mode = (
            self._pos,
            float(target),
            self.clock.monotonic(),
            mode,
        )
        self.moves += 1
        span = self._target - self._start
        self.recent_moves = [
            *self.recent_moves[-7:],
            Move(self._t0, span * self.pulse_deg, abs(span) / self.velocity_pps),
        ]
        if target != self._pos:
            self.direction = 1.0 if target > self._pos else -1.0

    def move_to(self, target: int) -> int:
        """Start a move; the error code (0 when started)."""
        with self._lock:
            self._update()
            if self._mode in (ctl.STATE_MOVING, ctl.STATE_HOMING):
                return ctl.ERR_BUSY
            if not self.homed:
                return ctl.ERR_NOT_HOMED
            if self.soft is not None and not self.soft[0] <= target <= self.soft[1]:
                return ctl.ERR_SOFT_LIMIT
            if self._into_hard_limit(target):
                return ctl.ERR_HARD_LIMIT
            self._go(target, ctl.STATE_MOVING)
            return ctl.ERR_NONE

    def _into_hard_limit(self, target: int) -> bool:
        """Whether an axis stopped on a hard limit is asked further into it (only moves back out
        are let through)."""
        if self._mode == ctl.STATE_HARD_LIMIT and self.hard is not None:
            at_low = self._pos <= self.hard[0]
            if (at_low and target <= self._pos) or (not at_low and target >= self._pos):
                return True
        return False

    def home(self) -> int:
        with self._lock:
            self._update()
            if self._mode in (ctl.STATE_MOVING, ctl.STATE_HOMING):
                return ctl.ERR_BUSY
            self._go(0.0, ctl.STATE_HOMING)
            return ctl.ERR_NONE

    def stop(self) -> None:
        with self._lock:
            self._update()
            if self._mode in (ctl.STATE_MOVING, ctl.STATE_HOMING):
                self._pos = float(round(self._pos))
                self._mode = ctl.STATE_READY

    @property
    def deg(self) -> float:
        return self.position * self.pulse_deg


class StageWorld:
    """Two stacked swing stages (axis 1 upper x, axis 2 lower y) carrying a reference and a
    measurement sensor (and optionally an analog sensor behind an ADC), as the scenario
    describes."""

    def __init__(
        self,
        scenario: StageScenario,
        clock: Clock,
        velocity_pps: int = 4000,
        adc_scenario: ScaleScenario | None = None,
    ) -> None:
        self.scenario = scenario
        self.clock = clock
        self.bench = hardware_of(scenario)
        self.effects: EffectSet = effect_set(scenario)
        self.geometry = StageGeometry.from_effects(self.bench, self.effects)
        self.settling = settling_of(self.effects)
        self.rng = np.random.default_rng(scenario.seed)
        self.t0 = clock.monotonic()
        self._lock = threading.Lock()
        self._batches: dict[str, _Batch] = {}
        self._last_read: dict[str, tuple[float, tuple[object, ...]]] = {}
        self._true_tilt: tuple[tuple[object, ...], tuple[float, float]] | None = None
        # the stage's positioning error of the present stand: drawn once when a stand begins, shared
        # by everything on the table and constant until the next move (a repeatability, not a
        # jitter) (by stand, the last few: a reader that took its stand's key just before a move
        # ended must not make the present stand draw again)
        self._stands: OrderedDict[tuple[object, ...], tuple[float, float]] = OrderedDict()
        # truth a bench never shows: what the settling transient added to the readings, (bench
        # times, stage x, stage y), kept only when a benchmark sets a list here
        self.transient_log: list[tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
        travel = self.bench.travel_deg
        self.axes: dict[int, Axis] = {}
        for n, pulse in ((1, self.bench.pulse_x_deg), (2, self.bench.pulse_y_deg)):
            soft = round(travel / pulse)
            hard = round((travel + 0.5) / pulse)
            self.axes[n] = Axis(clock, pulse, velocity_pps, (-soft, soft), (-hard, hard))
            self.axes[n].homed = scenario.controller_homed  # false: moves are refused until homed
        self.adc_scenario = adc_scenario
        if adc_scenario is not None:
            self.analog: AnalogSensor = hardware_of(adc_scenario)
            self.analog_effects = effect_set(adc_scenario)

    def t_s(self) -> float:
        return self.clock.monotonic() - self.t0

    def temp_c(self) -> float:
        return float(temperature(self.scenario.environment, np.array([self.t_s()]))[0])

    @property
    def pose_deg(self) -> tuple[float, float]:
        """Where the stages are (x upper, y lower), in degrees."""
        return self.axes[1].deg, self.axes[2].deg

    def _stand_key(self) -> tuple[object, ...]:
        return (
            *self.pose_deg,
            self.axes[1].direction,
            self.axes[2].direction,
            self.axes[1].moves,
            self.axes[2].moves,
        )

    def positioning_error_deg(self) -> tuple[float, float]:
        """The stage's positioning error (x, y) while it stands where it stands: one draw per
        stand."""
        key = self._stand_key()
        with self._lock:
            if key not in self._stands:
                sigma = self.effects.get("noise", "stage_sigma_deg")
                drawn = self.rng.normal(0.0, sigma, 2) if sigma > 0 else np.zeros(2)
                self._stands[key] = (float(drawn[0]), float(drawn[1]))
                while len(self._stands) > STANDS_KEPT:
                    self._stands.popitem(last=False)
            return self._stands[key]

    def sample(self, noisy: bool = True) -> dict[str, float]:
        """Both sensors' readings and the true table tilt at the present pose (the stand's
        positioning error in both; `noisy=False` leaves out the sensors' own noise)."""
        x_deg, y_deg = self.pose_deg
        error = self.positioning_error_deg()
        with self._lock:
            out = simulate_stage(
                self.bench,
                self.effects,
                [x_deg],
                [y_deg],
                [self.axes[1].direction],
                [self.axes[2].direction],
                [self.temp_c()],
                [self.t_s()],
                rng=self.rng if noisy else None,
                geometry=self.geometry,
                positioning_error_deg=error,
            )
        return {k: float(values[0]) for k, values in out.items()}

    def reading_deg(self, prefix: str, at_s: float | None = None) -> tuple[float, float]:
        """One sensor's reading (`ref` or `meas`) now, or at bench time `at_s` (the clock's: a frame
        sent in a burst is read at the time it was due), at the present pose. At rest the sensor's
        next readings are computed in one batch, at the bench times its output interval will ask for
        them, and handed out in turn; a move, a read outside the batch's time span or its end starts
        a new one. So every reading belongs to the pose it is read at, and to its time within the
        batch's span (READINGS_PER_BATCH output intervals; what changes with time, temperature,
        drifts by hours)."""
        x_deg, y_deg = self.pose_deg
        pose = (x_deg, y_deg, self.axes[1].direction, self.axes[2].direction)
        t = self.t_s() if at_s is None else at_s - self.t0
        error = self.positioning_error_deg()
        stand = self._stand_key()  # a batch belongs to one stand: a move away and back is another
        with self._lock:
            last = self._last_read.get(prefix)
            self._last_read[prefix] = (t, stand)
            batch = self._batches.get(prefix)
            if batch is not None and self._still_serves(batch, stand, t):
                batch.next += 1
                return batch.xy[batch.next - 1]
            # the interval the sensor asks at, from its last two reads at rest; one point while
            # moving
            at_rest = last is not None and last[1] == stand and 0.0 < t - last[0] < 1.0
            n = READINGS_PER_BATCH if at_rest else 1
            assert last is not None or n == 1
            dt = (t - last[0]) if at_rest and last is not None else 0.0
            times = t + dt * np.arange(n)
            sx, sy = self._settling_deg(times)
            out = simulate_stage(
                self.bench,
                self.effects,
                np.full(n, x_deg) + sx,
                np.full(n, y_deg) + sy,
                np.full(n, pose[2]),
                np.full(n, pose[3]),
                temperature(self.scenario.environment, times),
                times,
                rng=self.rng,
                geometry=self.geometry,
                positioning_error_deg=error,
            )
            batch = _Batch(stand, times, out[f"{prefix}_x_deg"], out[f"{prefix}_y_deg"])
            batch.next = 1
            self._batches[prefix] = batch
            return batch.xy[0]

    def _still_serves(self, batch: _Batch, stand: tuple[object, ...], t: float) -> bool:
        """Whether a sensor's batch hands out the next reading: made at this stand, readings left,
        and `t` within its time span (give or take one output interval)."""
        return (
            batch.pose == stand
            and batch.next < len(batch.xy)
            and batch.t_s[0] - self._dt_s(batch) <= t <= batch.t_s[-1] + self._dt_s(batch)
        )

    def _settling_deg(self, times: np.ndarray) -> tuple[np.ndarray | float, np.ndarray | float]:
        """Each stage's settling transient at bench times `times` (world seconds), as an angle of
        that stage."""
        if self.settling.is_instant:
            return 0.0, 0.0
        at = times + self.t0
        out = []
        for n in (1, 2):
            moves = recent(self.settling, self.axes[n].recent_moves, float(at[0]))
            out.append(transient_deg(self.settling, moves, at) if moves else 0.0)
        if self.transient_log is not None:
            x_deg, y_deg = (np.broadcast_to(part, at.shape).astype(float) for part in out)
            self.transient_log.append((at, x_deg, y_deg))
        return out[0], out[1]

    @staticmethod
    def _dt_s(b: _Batch) -> float:
        """The batch's spacing: one output interval."""
        return float(b.t_s[1] - b.t_s[0]) if len(b.t_s) > 1 else 0.0

    def true_tilt_deg(self) -> tuple[float, float]:
        """The table's true tilt as it stands: the geometry at the angles the stages really reached,
        the stand's positioning error included (no sensor noise, time or temperature), so one per
        stand."""
        key = self._stand_key()
        cached = self._true_tilt
        if cached is not None and cached[0] == key:
            return cached[1]
        sample = self.sample(noisy=False)
        tilt = sample["tilt_x_deg"], sample["tilt_y_deg"]
        self._true_tilt = (key, tilt)
        return tilt

    def aimed_tilt_deg(self) -> tuple[float, float]:
        """The table tilt the stage's present angles make without this stand's positioning error:
        where a levelling model's commands put the table, its stage's repeatability left out (what
        judges the model, not the stage)."""
        x_deg, y_deg = self.pose_deg
        with self._lock:
            out = simulate_stage(
                self.bench,
                self.effects,
                [x_deg],
                [y_deg],
                [self.axes[1].direction],
                [self.axes[2].direction],
                [self.temp_c()],
                [self.t_s()],
                rng=None,
                geometry=self.geometry,
                positioning_error_deg=(0.0, 0.0),
            )
        return float(out["tilt_x_deg"][0]), float(out["tilt_y_deg"][0])

    def adc_counts(self, conversions: int) -> float:
        """The analog sensor on the table (sensing x) behind the 12-bit ADC: one or a mean of n
        conversions."""
        assert self.adc_scenario is not None
        tilt_arcsec = self.true_tilt_deg()[0] * 3600.0
        with self._lock:
            out = simulate_scale(
                self.analog,
                self.analog_effects,
                np.full(conversions, tilt_arcsec),
                self.adc_scenario.bench.start_arcsec,
                np.full(conversions, self.temp_c()),
                self.rng,
            )
        return float(np.mean(out["reading"]))


class RotaryWorld:
    """A rotary table (controller axis 3, no limits) carrying a triaxial module about an inclined
    axis (rotation scenario) and RS-485 inclinometers read in symmetric positions (turntable
    scenario)."""

    def __init__(
        self,
        rotation: RotationScenario,
        turntable: TurntableScenario,
        clock: Clock,
        velocity_pps: int = 20_000,
        pulse_deg: float = 0.001,
        bus_addresses: tuple[int, ...] = (1, 2, 3),
    ) -> None:
        self.clock = clock
        self.rotation = rotation
        self.turntable = turntable
        self.rot_bench = hardware_of(rotation)
        self.rot_effects = effect_set(rotation)
        self.tt_effects = effect_set(turntable)
        base: TurntableInclinometer = hardware_of(turntable)
        # Each instrument on the bus sits at its own azimuth on the table.
        self.tt_sensors = {
            address: TurntableInclinometer(
                base.beta_deg + 40.0 * i, base.epsilon_deg, base.m1, base.m2
            )
            for i, address in enumerate(bus_addresses)
        }
        cycle = turntable.grid.cycles[0]
        self.axis_tilt_arcsec = (cycle.north_arcsec, cycle.east_arcsec)
        self.rng = np.random.default_rng(rotation.seed)
        self._lock = threading.Lock()
        self.axes = {3: Axis(clock, pulse_deg, velocity_pps, None, None)}
        self.t0 = clock.monotonic()

    @property
    def table_deg(self) -> float:
        return self.axes[3].deg

    @property
    def pose_deg(self) -> float:
        return self.table_deg

    def temp_c(self) -> float:
        return 20.0

    def sines(self, noisy: bool = True) -> tuple[float, float, float]:
        with self._lock:
            out = simulate_rotation(
                self.rot_bench, self.rot_effects, [self.table_deg], self.rng if noisy else None
            )
        return float(out["sx"][0]), float(out["sy"][0]), float(out["sz"][0])

    def turntable_mrad(self, address: int, noisy: bool = True) -> tuple[float, float]:
        sensor = self.tt_sensors[address]
        fx = self.tt_effects
        n1, n2 = turntable_readings(
            sensor,
            self.table_deg,
            *self.axis_tilt_arcsec,
            fx.get("zero_offset", "z1"),
            fx.get("zero_offset", "z2"),
        )
        sigma, res = fx.get("noise", "reading_sigma"), fx.get("noise", "resolution")
        out = []
        with self._lock:
            for n in (float(n1), float(n2)):
                if noisy and sigma > 0:
                    n += float(self.rng.normal(0.0, sigma))
                if res > 0:
                    n = round(n / res) * res
                out.append(n)
        return out[0], out[1]


def stage_scenario(name: str) -> StageScenario:
    sc = load_scenario(name)
    if not isinstance(sc, StageScenario):
        raise InputError(
            f"scenario {name!r} is a {sc.kind} scenario; a stage bench needs a stage scenario"
        )
    return sc


def rotary_scenarios(name: str) -> tuple[RotationScenario, TurntableScenario]:
    """The scenario named drives its instrument; the other instrument of the rotary bench follows
    its preset."""
    sc = load_scenario(name)
    if isinstance(sc, RotationScenario):
        other = load_scenario("seed004")
        assert isinstance(other, TurntableScenario)
        return sc, other
    if isinstance(sc, TurntableScenario):
        other = load_scenario("seed002-sim")
        assert isinstance(other, RotationScenario)
        return other, sc
    raise InputError(
        f"scenario {name!r} is a {sc.kind} scenario; a rotary bench needs a rotation or turntable "
        "scenario"
    )


__all__ = [
    "ARCSEC_PER_RAD",
    "NO_LIMIT",
    "Axis",
    "RotaryWorld",
    "StageWorld",
    "rotary_scenarios",
    "stage_scenario",
]
