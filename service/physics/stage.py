"""Forward model of two stacked swing stages carrying a reference and a measurement sensor.

docs/models.md §2: the lower stage tilts the assembly about the table X axis (the stage y
angle), the upper stage rides on it and tilts the table about Y (the stage x angle); ideal
orientation R = Rx(-θy)·Ry(θx). Here every effect of §5 is a separately switchable term.

The chain, world ← table:  R_desk · Rot(u_lower, θy) · Rot(u_upper, θx) · R_top, and a sensor
axis a = R_world_table · R_seat · axis. Only a_z is needed (reading = asin(-a_z)), and a_z is a
linear functional of the rotated vector, so the whole chain reduces to a few (N, 3) products:
this is what keeps the model above a million points per second.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.physics.effects import EffectSet
from service.physics.inclinometer import apply_reading_errors, sensor_axes
from service.physics.rotations import plane_tilt, rx, ry, rz, unit

SENSORS = ("ref", "meas")
ASSUMED_BENCH_SOURCE = "assumed (none stated): the seed 000 bench"
PULSE_TOL = 0.01  # of a pulse: commands written with 6 decimals still read back as whole pulses
COMMON_GEAR_RATIOS = (
    30,
    45,
    50,
    60,
    90,
    100,
    120,
    144,
    180,
    200,
    240,
    250,
    288,
    300,
    320,
    360,
    400,
    450,
    500,
    540,
    600,
    720,
    900,
)


@dataclass(frozen=True)
class StageBench:
    """Fixed hardware of a stacked swing-stage bench (seed 000 §1).

    The one definition of the stage hardware: the scenario files' `bench` section and the bench
    configuration's `hardware` table are validated against these fields and bounds.
    """

    upper_gear_ratio: float = field(default=320.0, metadata={"gt": 1, "le": 10_000})
    lower_gear_ratio: float = field(default=450.0, metadata={"gt": 1, "le": 10_000})
    step_angle_deg: float = field(default=1.8, metadata={"gt": 0, "le": 90})
    microsteps: int = field(default=8, metadata={"ge": 1, "le": 256})
    travel_deg: float = field(default=15.0, metadata={"gt": 0, "le": 90})
    # measurement sensor mounted upside down, turned about its "x" or "y" axis
    meas_flip: str = field(default="none", metadata={"choices": ("none", "x", "y")})
    temp_ref_c: float = field(default=20.0, metadata={"ge": -50, "le": 150})

    @property
    def pulse_x_deg(self) -> float:
        """One pulse of the upper stage: φ / (x · c) (0.000703 deg at 320:1)."""
        return self.step_angle_deg / (self.microsteps * self.upper_gear_ratio)

    @property
    def pulse_y_deg(self) -> float:
        return self.step_angle_deg / (self.microsteps * self.lower_gear_ratio)

    @property
    def worm_period_x_deg(self) -> float:
        """Output angle per worm turn: 360 deg / gear ratio (1.125 deg at 320:1)."""
        return 360.0 / self.upper_gear_ratio

    @property
    def worm_period_y_deg(self) -> float:
        return 360.0 / self.lower_gear_ratio

    def quantise(
        self, cmd_x_deg: ArrayLike, cmd_y_deg: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Commands as the controller executes them: whole pulses."""
        px, py = self.pulse_x_deg, self.pulse_y_deg
        return np.rint(np.asarray(cmd_x_deg) / px) * px, np.rint(np.asarray(cmd_y_deg) / py) * py

    def describe(self) -> str:
        """The hardware in the lab's words, for messages and reports."""
        flip = (
            ""
            if self.meas_flip == "none"
            else f", measurement sensor turned about {self.meas_flip}"
        )
        return (
            f"upper {self.upper_gear_ratio:g}:1, lower {self.lower_gear_ratio:g}:1, "
            f"{self.step_angle_deg:g} deg steps at {self.microsteps} microsteps (pulses "
            f"{self.pulse_x_deg:.9g} / {self.pulse_y_deg:.9g} deg), travel ±{self.travel_deg:g} "
            f"deg{flip}"
        )

    def record(self, source: str) -> dict[str, float | str]:
        """The bench as models and reports record it: hardware, derived pulses and worm periods, and
        its source."""
        return {
            **asdict(self),
            "pulse_x_deg": self.pulse_x_deg,
            "pulse_y_deg": self.pulse_y_deg,
            "worm_period_x_deg": self.worm_period_x_deg,
            "worm_period_y_deg": self.worm_period_y_deg,
            "source": source,
        }

    def pulse_mismatch(self, cmd_x_deg: ArrayLike, cmd_y_deg: ArrayLike) -> str | None:
        """Why recorded commands are not whole pulses of this bench (None when they are).

        A controller executes whole pulses, so commands recorded from a bench of this hardware
        are whole multiples of its pulse; commands that are not came from another bench (other
        gear ratio or microsteps) or were recorded as requested rather than executed.
        """
        for axis, name, cmd, pulse, ratio in (
            ("x", "stage_x_deg", cmd_x_deg, self.pulse_x_deg, self.upper_gear_ratio),
            ("y", "stage_y_deg", cmd_y_deg, self.pulse_y_deg, self.lower_gear_ratio),
        ):
            commands = np.asarray(cmd, dtype=float)
            frac = np.abs(commands / pulse - np.rint(commands / pulse))
            off = np.flatnonzero(frac > PULSE_TOL)
            if off.size == 0:
                continue
            i = int(off[0])
            fits = sorted(
                (
                    gear
                    for gear in COMMON_GEAR_RATIOS
                    if np.all(_whole(commands, self.step_angle_deg / (self.microsteps * gear)))
                ),
                # nearest to the assumed ratio first
                key=lambda gear: abs(np.log(gear / ratio)),
            )
            fits_micro = [
                m
                for m in (1, 2, 4, 8, 16, 32, 64, 128, 256)
                if np.all(_whole(commands, self.step_angle_deg / (m * ratio)))
            ]
            if fits:
                hint = (
                    "they are whole pulses at gear ratio "
                    f"{', '.join(f'{gear:g}:1' for gear in fits[:4])} "
                    f"({self.microsteps} microsteps of {self.step_angle_deg:g} deg)"
                )
            elif fits_micro:
                hint = (
                    f"they are whole pulses at {', '.join(map(str, fits_micro[:3]))} "
                    f"microsteps ({ratio:g}:1)"
                )
            else:
                hint = (
                    "they are whole pulses of no common gear ratio: they may be requested "
                    "rather than executed angles"
                )
            return (
                f"{name} {commands[i]:.9g} at row {i + 1} is {commands[i] / pulse:.3f} pulses "
                f"of the {axis} stage ({pulse:.9g} deg = {self.step_angle_deg:g} deg / "
                f"({self.microsteps} microsteps x {ratio:g}:1)), not a whole number "
                f"({off.size} of {commands.size} rows): "
                "the data likely come from a bench with another gear ratio or microstepping; "
                f"{hint}"
            )
        return None


def _whole(cmd: NDArray[np.float64], pulse: float) -> NDArray[np.bool_]:
    return np.abs(cmd / pulse - np.rint(cmd / pulse)) <= PULSE_TOL


@dataclass(frozen=True)
class StageGeometry:
    """The constant rotations of the chain, resolved from the effect set once per bench."""

    desk: NDArray[np.float64]
    top: NDArray[np.float64]
    u_lower: NDArray[np.float64]
    u_upper: NDArray[np.float64]
    seat: dict[str, NDArray[np.float64]]
    # per sensor: (2, 3) x and y sensing axes in the seat frame
    axes: dict[str, NDArray[np.float64]]
    truth_axes: NDArray[np.float64]  # orthogonal reference axes: the definition of table tilt
    coupling: bool

    @classmethod
    def from_effects(cls, bench: StageBench, fx: EffectSet) -> StageGeometry:
        rad = np.radians

        def g(e: str, p: str) -> float:
            return float(fx.get(e, p))

        desk = plane_tilt(
            rad(g("mounting_tilt", "desk_x_deg")), rad(g("mounting_tilt", "desk_y_deg"))
        )
        top = plane_tilt(rad(g("mounting_tilt", "top_x_deg")), rad(g("mounting_tilt", "top_y_deg")))
        u_lower = unit(
            rz(rad(g("axis_misalignment", "lower_yaw_deg")))
            @ ry(rad(g("axis_misalignment", "lower_pitch_deg")))
            @ np.array([-1.0, 0.0, 0.0])
        )
        u_upper = unit(
            rz(rad(g("axis_misalignment", "perpendicularity_deg")))
            @ rx(rad(g("axis_misalignment", "upper_pitch_deg")))
            @ np.array([0.0, 1.0, 0.0])
        )
        seat: dict[str, NDArray[np.float64]] = {}
        axes: dict[str, NDArray[np.float64]] = {}
        for sensor in SENSORS:
            seat[sensor] = plane_tilt(
                rad(g("mounting_tilt", f"{sensor}_x_deg")),
                rad(g("mounting_tilt", f"{sensor}_y_deg")),
            )
            flip = bench.meas_flip if sensor == "meas" else "none"
            axes[sensor] = sensor_axes(
                rad(g("sensor_yaw", f"{sensor}_deg")),
                rad(g("non_orthogonality", f"{sensor}_deg")),
                flip,
            )
        truth_axes = sensor_axes(rad(g("sensor_yaw", "ref_deg")), 0.0)
        return cls(
            desk,
            top,
            u_lower,
            u_upper,
            seat,
            axes,
            truth_axes,
            bool(fx.get("offaxis_coupling", "enabled")),
        )

    def axis_z(
        self,
        vectors_table: NDArray[np.float64],
        theta_x: NDArray[np.float64],
        theta_y: NDArray[np.float64],
    ) -> NDArray[np.float64]:
        """World z of table-frame vectors (K, 3) at stage angles (N,) [rad] -> (N, K)."""
        desk_z = self.desk[2]
        ul, uu = self.u_lower, self.u_upper
        cy, sy = np.cos(theta_y), np.sin(theta_y)
        # desk_z · Rot(ul, θy) w = w · z_row(θy)
        z_row = (
            cy[:, None] * desk_z
            + sy[:, None] * np.cross(desk_z, ul)
            + ((1.0 - cy) * (ul @ desk_z))[:, None] * ul
        )
        vectors = vectors_table
        cos_term = z_row @ vectors.T
        sin_term = z_row @ np.cross(uu, vectors).T
        axial_term = z_row @ uu
        cx, sx = np.cos(theta_x), np.sin(theta_x)
        z: NDArray[np.float64] = (
            cx[:, None] * cos_term
            + sx[:, None] * sin_term
            + ((1.0 - cx) * axial_term)[:, None] * (vectors @ uu)[None, :]
        )
        return z

    def readings_deg(
        self, theta_x: NDArray[np.float64], theta_y: NDArray[np.float64]
    ) -> dict[str, NDArray[np.float64]]:
        """Geometric (error-free) readings of every sensor axis and the true table tilt."""
        if not self.coupling:
            theta_x = np.radians(
                offaxis_inverse_deg(np.degrees(theta_x), np.degrees(theta_y), clip=True)
            )
        vecs = [self.top @ self.seat[sensor] @ self.axes[sensor].T for sensor in SENSORS]
        vecs.append(self.top @ self.seat["ref"] @ self.truth_axes.T)
        table_axes = np.concatenate(vecs, axis=1).T  # (6, 3)
        deg = np.degrees(np.arcsin(np.clip(-self.axis_z(table_axes, theta_x, theta_y), -1.0, 1.0)))
        names = ("ref_x", "ref_y", "meas_x", "meas_y", "tilt_x", "tilt_y")
        return {n: deg[:, i] for i, n in enumerate(names)}


def stage_angles_deg(
    bench: StageBench,
    fx: EffectSet,
    cmd_x_deg: ArrayLike,
    cmd_y_deg: ArrayLike,
    dir_x: ArrayLike = 0,
    dir_y: ArrayLike = 0,
    rng: np.random.Generator | None = None,
    stand: ArrayLike | None = None,
    positioning_error_deg: tuple[float, float] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Angles the stages really reach for the given commands and approach directions.

    The positioning error (`stage_sigma_deg`, a repeatability) is drawn once per move: per row, or
    with `stand` (the move each row was read at) once per stand, shared by the rows read there. A
    caller that keeps the stand itself (the simulated bench, whose stage stands between moves) gives
    the error of the present stand as `positioning_error_deg` (x, y), and nothing is drawn.
    """
    nom_x, nom_y = bench.quantise(cmd_x_deg, cmd_y_deg)
    out = []
    for ax, nom, direction, period in (
        ("x", nom_x, dir_x, bench.worm_period_x_deg),
        ("y", nom_y, dir_y, bench.worm_period_y_deg),
    ):
        ang = nom * (1.0 + fx.get("stage_scale", ax))
        ang = ang - np.asarray(direction, dtype=float) * fx.get("backlash", f"{ax}_deg") / 2.0
        amp = fx.get("periodic_error", f"{ax}_amp_deg")
        if amp:
            ang = ang + amp * np.sin(
                2 * np.pi * nom / period + np.radians(fx.get("periodic_error", f"{ax}_phase_deg"))
            )
        sigma = fx.get("noise", "stage_sigma_deg")
        if positioning_error_deg is not None:
            ang = ang + positioning_error_deg[0 if ax == "x" else 1]
        elif rng is not None and sigma > 0:
            if stand is None:
                ang = ang + rng.normal(0.0, sigma, np.shape(ang))
            else:
                moves, which = np.unique(np.asarray(stand), return_inverse=True)
                ang = ang + rng.normal(0.0, sigma, moves.size)[which.reshape(np.shape(stand))]
        out.append(np.asarray(ang, dtype=float))
    return out[0], out[1]


def _drift(
    fx: EffectSet, sensor: str, axis: str, t_s: NDArray[np.float64], rng: np.random.Generator | None
) -> NDArray[np.float64]:
    drift = fx.get("time_drift", f"{sensor}_{axis}_deg_per_h") * t_s / 3600.0
    rw = fx.get("time_drift", "random_walk_deg_per_sqrt_h")
    if rng is not None and rw > 0 and t_s.size:
        dt_h = np.diff(t_s, prepend=t_s[0]) / 3600.0
        drift = drift + np.cumsum(rng.normal(0.0, 1.0, t_s.shape) * rw * np.sqrt(dt_h))
    return drift


def simulate_stage(
    bench: StageBench,
    fx: EffectSet,
    cmd_x_deg: ArrayLike,
    cmd_y_deg: ArrayLike,
    dir_x: ArrayLike = 0,
    dir_y: ArrayLike = 0,
    temp_c: ArrayLike | None = None,
    t_s: ArrayLike | None = None,
    rng: np.random.Generator | None = None,
    geometry: StageGeometry | None = None,
    stand: ArrayLike | None = None,
    positioning_error_deg: tuple[float, float] | None = None,
) -> dict[str, NDArray[np.float64]]:
    """Readings of both sensors (and the true table tilt) at each commanded point.

    `rng=None` gives the noiseless bench. Both sensors ride on one table: they see the same
    positioning error, drawn once per row (each row a move) or, with `stand`, once per stand.
    Returns arrays keyed by dataset column names plus `tilt_x_deg`, `tilt_y_deg` (truth) and
    `actual_x_deg`, `actual_y_deg` (stage angles).
    """
    cmd_x = np.atleast_1d(np.asarray(cmd_x_deg, dtype=float))
    cmd_y = np.atleast_1d(np.asarray(cmd_y_deg, dtype=float))
    n = np.broadcast_shapes(cmd_x.shape, cmd_y.shape)
    temp = np.broadcast_to(
        np.asarray(bench.temp_ref_c if temp_c is None else temp_c, dtype=float), n
    )
    t = np.broadcast_to(np.asarray(0.0 if t_s is None else t_s, dtype=float), n)
    geometry = geometry or StageGeometry.from_effects(bench, fx)
    act_x, act_y = stage_angles_deg(
        bench,
        fx,
        cmd_x,
        cmd_y,
        dir_x,
        dir_y,
        rng,
        None if stand is None else np.broadcast_to(np.asarray(stand), n),
        positioning_error_deg,
    )
    geo = geometry.readings_deg(
        np.radians(np.broadcast_to(act_x, n)), np.radians(np.broadcast_to(act_y, n))
    )
    dT = temp - bench.temp_ref_c
    out = {
        "tilt_x_deg": geo["tilt_x"],
        "tilt_y_deg": geo["tilt_y"],
        "actual_x_deg": np.broadcast_to(act_x, n).copy(),
        "actual_y_deg": np.broadcast_to(act_y, n).copy(),
    }
    for sensor in SENSORS:
        sigma = fx.get("noise", f"{sensor}_sigma_deg")
        for axis in ("x", "y"):
            noise = rng.normal(0.0, sigma, n) if (rng is not None and sigma > 0) else 0.0
            out[f"{sensor}_{axis}_deg"] = apply_reading_errors(
                geo[f"{sensor}_{axis}"],
                zero_deg=fx.get("zero_offset", f"{sensor}_{axis}_deg"),
                scale=fx.get("scale_factor", f"{sensor}_{axis}"),
                quad_per_deg=fx.get("sensor_nonlinearity", f"{sensor}_{axis}_per_deg"),
                temp_delta_k=dT,
                zero_per_k=fx.get("temperature_drift", f"{sensor}_{axis}_deg_per_k"),
                scale_per_k=fx.get("temperature_drift", f"{sensor}_scale_per_k"),
                drift_deg=_drift(fx, sensor, axis, t, rng),
                noise_deg=noise,
                resolution_deg=fx.get("noise", f"{sensor}_resolution_deg"),
            )
    return out


# --- seed 000 eqs. (9) and (10): the off-axis relation of the stacked stages, the one place it is
# written ---
def offaxis_reading_deg(theta_x_deg: ArrayLike, theta_y_deg: ArrayLike) -> NDArray[np.float64]:
    """Eq. (9): the x reading of an ideal stacked bench, asin(sin θx · cos θy).

    The lower stage tilts the upper stage's axis with it, so the upper stage's angle reaches the
    table's x tilt only scaled by cos θy; this is also the angle an uncoupled bench would need.
    """
    tx, ty = np.radians(theta_x_deg), np.radians(theta_y_deg)
    reading: NDArray[np.float64] = np.degrees(
        np.arcsin(np.clip(np.sin(tx) * np.cos(ty), -1.0, 1.0))
    )
    return reading


def offaxis_error_deg(theta_x_deg: ArrayLike, theta_y_deg: ArrayLike) -> NDArray[np.float64]:
    """Eq. (10): θx − asin(sin θx cos θy), the x reading lost to the lower stage's tilt.

    Seed 000 prints it as θx − sign(θx)·atan(sqrt(q / (1 − q))) with q = sin²θx cos²θy: the same
    value.
    """
    return np.asarray(theta_x_deg, dtype=float) - offaxis_reading_deg(theta_x_deg, theta_y_deg)


def offaxis_inverse_deg(
    x_reading_deg: ArrayLike, theta_y_deg: ArrayLike, *, clip: bool = False
) -> NDArray[np.float64]:
    """Eq. (9) inverted exactly: the upper-stage angle giving x reading X at lower angle θy,
    asin(sin X / cos θy).

    NaN where no upper-stage angle gives X (|sin X / cos θy| > 1; the caller names those rows), or
    with clip=True the nearest reachable angle (a starting point for a solver).
    """
    sine = np.sin(np.radians(x_reading_deg)) / np.cos(np.radians(theta_y_deg))
    sine = np.clip(sine, -1.0, 1.0) if clip else np.where(np.abs(sine) > 1.0, np.nan, sine)
    angle: NDArray[np.float64] = np.degrees(np.arcsin(sine))
    return angle
