"""The one registry of physical effects (docs/models.md §5), per dataset kind.

Every effect is a named group of parameters with units and allowed ranges. A scenario
switches an effect on by naming it; parameters it leaves out take their default. The
scenario validator, the JSON Schema under docs/, the simulator and the discrepancy
workflow all read this table, so a name or a range is written down exactly once.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

EFFECT_NAMES = (
    "zero_offset",
    "scale_factor",
    "non_orthogonality",
    "sensor_yaw",
    "mounting_tilt",
    "axis_misalignment",
    "stage_scale",
    "offaxis_coupling",
    "backlash",
    "periodic_error",
    "sensor_nonlinearity",
    "temperature_drift",
    "time_drift",
    "noise",
    "settling",
)


@dataclass(frozen=True)
class Param:
    name: str
    unit: str
    lo: float
    hi: float
    default: float | bool = 0.0
    doc: str = ""

    @property
    def is_bool(self) -> bool:
        return isinstance(self.default, bool)


@dataclass(frozen=True)
class Effect:
    name: str
    doc: str
    params: tuple[Param, ...]
    default_on: bool = False

    def param(self, name: str) -> Param:
        for candidate in self.params:
            if candidate.name == name:
                return candidate
        raise KeyError(name)


def _p(
    name: str, unit: str, lo: float, hi: float, doc: str = "", default: float | bool = 0.0
) -> Param:
    return Param(name, unit, lo, hi, default, doc)


def _per_sensor(
    fmt: str,
    unit: str,
    lo: float,
    hi: float,
    doc: str,
    sensors: tuple[str, ...] = ("ref", "meas"),
    axes: tuple[str, ...] = ("x", "y"),
) -> tuple[Param, ...]:
    return tuple(
        _p(fmt.format(s=sensor, a=axis), unit, lo, hi, doc.format(s=sensor, a=axis))
        for sensor in sensors
        for axis in axes
    )


# --- stacked swing stages (seed 000, docs/models.md §2)
# ---------------------------------------------
STAGE_EFFECTS: dict[str, Effect] = {
    effect.name: effect
    for effect in (
        Effect(
            "zero_offset",
            "constant added to a sensor axis reading",
            _per_sensor(
                "{s}_{a}_deg", "deg", -2.0, 2.0, "zero offset of the {s} sensor's {a} axis"
            ),
        ),
        Effect(
            "scale_factor",
            "sensor axis gain error: reading = (1 + k) * angle",
            _per_sensor(
                "{s}_{a}", "1", -0.05, 0.05, "relative gain error of the {s} sensor's {a} axis"
            ),
        ),
        Effect(
            "non_orthogonality",
            "the sensor's y axis is turned by this angle from 90 deg to its x axis",
            (_p("ref_deg", "deg", -3.0, 3.0), _p("meas_deg", "deg", -3.0, 3.0)),
        ),
        Effect(
            "sensor_yaw",
            "sensor frame rotated about the table normal",
            (_p("ref_deg", "deg", -10.0, 10.0), _p("meas_deg", "deg", -10.0, 10.0)),
        ),
        Effect(
            "mounting_tilt",
            "a mounting plane not parallel to its neighbour; (x, y) is the tilt it adds to an x / "
            "y reading: "
            "desk under the bench, table top on the upper stage, seat of each sensor",
            tuple(
                _p(
                    f"{plane}_{axis}_deg",
                    "deg",
                    -3.0,
                    3.0,
                    f"tilt of the {plane} plane seen by {axis} readings",
                )
                for plane in ("desk", "top", "ref", "meas")
                for axis in ("x", "y")
            ),
        ),
        Effect(
            "axis_misalignment",
            "stage axes off their nominal directions: lower (y) axis yaw about the vertical and "
            "pitch out of the horizontal; upper (x) axis deviation from perpendicular to the "
            "lower axis and pitch out of the lower stage's plane",
            (
                _p("lower_yaw_deg", "deg", -3.0, 3.0),
                _p("lower_pitch_deg", "deg", -3.0, 3.0),
                _p("perpendicularity_deg", "deg", -3.0, 3.0),
                _p("upper_pitch_deg", "deg", -3.0, 3.0),
            ),
        ),
        Effect(
            "stage_scale",
            "stage angle per command differs from nominal: angle = (1 + k) * command",
            (_p("x", "1", -0.05, 0.05, "upper stage"), _p("y", "1", -0.05, 0.05, "lower stage")),
        ),
        Effect(
            "offaxis_coupling",
            "the stacked-stage geometry of docs/models.md §2 (x = asin(sin θx cos θy)); geometry, "
            "so on by default; "
            "off only builds an idealised bench whose upper stage is decoupled",
            (_p("enabled", "bool", 0, 1, "", default=True),),
            default_on=True,
        ),
        Effect(
            "backlash",
            "worm-gear lost motion: the stage lags the command by half the width, against the last "
            "move",
            (
                _p("x_deg", "deg", 0.0, 0.5, "full width, upper stage"),
                _p("y_deg", "deg", 0.0, 0.5, "full width, lower stage"),
            ),
        ),
        Effect(
            "periodic_error",
            "stage angle error periodic in the worm's turn (period 360 deg / gear ratio of output "
            "angle)",
            (
                _p("x_amp_deg", "deg", 0.0, 0.2),
                _p("y_amp_deg", "deg", 0.0, 0.2),
                _p("x_phase_deg", "deg", -180.0, 180.0),
                _p("y_phase_deg", "deg", -180.0, 180.0),
            ),
        ),
        Effect(
            "sensor_nonlinearity",
            "quadratic term of a sensor axis: reading += k * angle^2",
            _per_sensor("{s}_{a}_per_deg", "1/deg", -0.01, 0.01, "quadratic coefficient, {s} {a}"),
        ),
        Effect(
            "temperature_drift",
            "zero (deg/K) and scale (1/K) of a sensor change with temperature away from the "
            "bench's temp_ref_c",
            _per_sensor("{s}_{a}_deg_per_k", "deg/K", -0.05, 0.05, "zero coefficient, {s} {a}")
            + (
                _p("ref_scale_per_k", "1/K", -0.005, 0.005),
                _p("meas_scale_per_k", "1/K", -0.005, 0.005),
            ),
        ),
        Effect(
            "time_drift",
            "zero of a sensor wanders slowly with time: a linear rate plus a random walk",
            _per_sensor("{s}_{a}_deg_per_h", "deg/h", -0.5, 0.5, "zero drift rate, {s} {a}")
            + (_p("random_walk_deg_per_sqrt_h", "deg/sqrt(h)", 0.0, 0.1),),
        ),
        Effect(
            "noise",
            "white noise of each sensor reading (1 sigma), stage positioning repeatability (1 "
            "sigma) and sensor output resolution (quantisation step)",
            (
                _p("ref_sigma_deg", "deg", 0.0, 0.2),
                _p("meas_sigma_deg", "deg", 0.0, 0.2),
                _p("stage_sigma_deg", "deg", 0.0, 0.1),
                _p("ref_resolution_deg", "deg", 0.0, 0.01),
                _p("meas_resolution_deg", "deg", 0.0, 0.01),
            ),
        ),
        Effect(
            "settling",
            "what a reading shows in the seconds after a move: the table rings (amplitude per "
            "degree moved, frequency, 1/e decay time) and each sensor follows the table with a "
            "first-order time constant (service.physics.settling); a reading taken long after a "
            "move does not see it",
            (
                _p(
                    "sensor_time_constant_s",
                    "s",
                    0.0,
                    60.0,
                    "first-order time constant of each sensor's output",
                ),
                _p(
                    "ringing_amplitude_deg_per_deg",
                    "deg/deg",
                    0.0,
                    0.1,
                    "the table's ringing amplitude when a move ends, per degree moved",
                ),
                _p("ringing_frequency_hz", "Hz", 0.0, 200.0, "frequency of the table's ringing"),
                _p("ringing_decay_s", "s", 0.0, 60.0, "1/e decay time of the table's ringing"),
            ),
        ),
    )
}

_S_AXES = ("sx", "sy", "sz")

# --- rotation about an inclined axis (seed 002, docs/models.md §3); sensor errors in the sine
# domain ---
ROTATION_EFFECTS: dict[str, Effect] = {
    effect.name: effect
    for effect in (
        Effect(
            "zero_offset",
            "offset of a sensor output (sine units)",
            tuple(_p(axis, "1", -0.05, 0.05) for axis in _S_AXES),
        ),
        Effect(
            "scale_factor",
            "relative gain error of a sensor output",
            tuple(_p(axis, "1", -0.05, 0.05) for axis in _S_AXES),
        ),
        Effect(
            "sensor_nonlinearity",
            "quadratic term in the output: S += k * S^2",
            tuple(_p(axis, "1", -0.05, 0.05) for axis in _S_AXES),
        ),
        Effect(
            "noise",
            "white noise of each output, 1 sigma, in sine units (constant in S: an angle error "
            "that grows as 1/cos of the axis angle)",
            (_p("sigma_s", "1", 0.0, 0.01), _p("theta_ref_sigma_deg", "deg", 0.0, 1.0)),
        ),
    )
}

# --- analog sensor behind a 12-bit ADC (seed 003) ---------------------------------------------
SCALE_EFFECTS: dict[str, Effect] = {
    effect.name: effect
    for effect in (
        Effect(
            "zero_offset",
            "offset of the output, in ADC counts",
            (_p("counts", "count", -500.0, 500.0),),
        ),
        Effect("scale_factor", "relative gain error of the output", (_p("k", "1", -0.2, 0.2),)),
        Effect(
            "sensor_nonlinearity",
            "quadratic term of the output in the angle from the sensor's null: counts += k * "
            "angle^2",
            (_p("counts_per_arcsec2", "count/arcsec^2", -1e-3, 1e-3),),
        ),
        Effect(
            "temperature_drift",
            "zero of the output changes with temperature",
            (_p("counts_per_k", "count/K", -50.0, 50.0),),
        ),
        Effect(
            "noise",
            "white noise of the output (1 sigma, counts) and of the reference reading (arcsec)",
            (
                _p("reading_sigma_counts", "count", 0.0, 50.0),
                _p("ref_sigma_arcsec", "arcsec", 0.0, 30.0),
            ),
        ),
    )
}

# --- inclinometer on a turntable (seed 004, docs/models.md §4)
# ------------------------------------------
TURNTABLE_EFFECTS: dict[str, Effect] = {
    effect.name: effect
    for effect in (
        Effect(
            "zero_offset",
            "zero offsets z1, z2 (reading units)",
            (_p("z1", "reading", -10.0, 10.0), _p("z2", "reading", -10.0, 10.0)),
        ),
        Effect(
            "noise",
            "white noise of each reading (reading units, 1 sigma), of the star-derived reference "
            "(arcsec, 1 sigma), and reading resolution",
            (
                _p("reading_sigma", "reading", 0.0, 0.1),
                _p("ref_sigma_arcsec", "arcsec", 0.0, 5.0),
                _p("resolution", "reading", 0.0, 0.01),
            ),
        ),
        Effect(
            "time_drift",
            "zero drift of both readings between the two positions of a pair",
            (_p("reading_per_h", "reading/h", -1.0, 1.0),),
        ),
    )
}

EFFECTS_BY_KIND: dict[str, dict[str, Effect]] = {
    "stage": STAGE_EFFECTS,
    "rotation": ROTATION_EFFECTS,
    "scale": SCALE_EFFECTS,
    "turntable": TURNTABLE_EFFECTS,
}

assert all(name in EFFECT_NAMES for table in EFFECTS_BY_KIND.values() for name in table)


def _reject_unknown_effects(
    kind: str, table: Mapping[str, Effect], effects: Mapping[str, object]
) -> None:
    """A scenario naming an effect its kind does not have is an error, not a silent no-op."""
    unknown = [n for n in effects if n not in table]
    if unknown:
        raise KeyError(
            f"unknown effect {unknown[0]!r} for kind {kind!r}; known: {', '.join(table)}"
        )


def _resolved_params(name: str, eff: Effect, given: Mapping[str, float]) -> dict[str, float]:
    """Every parameter of one effect: the given values checked against its table, the rest at
    their defaults."""
    bad = [k for k in given if k not in {param.name for param in eff.params}]
    if bad:
        raise KeyError(f"effect {name!r} has no parameter {bad[0]!r}")
    return {param.name: given.get(param.name, param.default) for param in eff.params}


@dataclass(frozen=True)
class EffectSet:
    """Effect magnitudes of one bench: every parameter resolved, off effects at their defaults."""

    kind: str
    # a bool switch is a number too
    values: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    on: frozenset[str] = frozenset()

    @classmethod
    def from_mapping(
        cls, kind: str, effects: Mapping[str, Mapping[str, float]] | None = None
    ) -> EffectSet:
        table = EFFECTS_BY_KIND[kind]
        effects = dict(effects or {})
        _reject_unknown_effects(kind, table, effects)
        values: dict[str, dict[str, float]] = {}
        on = set()
        for name, eff in table.items():
            values[name] = _resolved_params(name, eff, dict(effects.get(name) or {}))
            if name in effects or eff.default_on:
                on.add(name)
        if name_off := [n for n in on if table[n].default_on and not all(values[n].values())]:
            on -= set(name_off)
        return cls(kind, values, frozenset(on))

    def get(self, effect: str, param: str) -> float:
        """The parameter's value if its effect is on, else the value meaning 'absent'."""
        eff = EFFECTS_BY_KIND[self.kind][effect]
        if effect not in self.on:
            spec = eff.param(param)
            return spec.default if not eff.default_on else (False if spec.is_bool else 0.0)
        return self.values[effect][param]


def markdown_tables() -> str:
    """The registry as Markdown tables (docs/physics.md embeds this text; a test keeps it
    current)."""
    out = []
    for kind, table in EFFECTS_BY_KIND.items():
        out.append(
            f"#### kind `{kind}`\n\n| effect | parameter | unit | range | default |\n| --- | --- | "
            "--- | --- | --- |"
        )
        for eff in table.values():
            for param in eff.params:
                rng = "true/false" if param.is_bool else f"{param.lo:g} .. {param.hi:g}"
                default = str(param.default).lower() if param.is_bool else f"{param.default:g}"
                out.append(f"| `{eff.name}` | `{param.name}` | {param.unit} | {rng} | {default} |")
        out.append("")
    return "\n".join(out)
