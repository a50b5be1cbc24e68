"""Scenario files: a bench, its effect magnitudes, the point grid, the environment and a seed.

The pydantic models are built from the effect registry (service.physics.effects), so the
allowed names and ranges, the JSON Schema in docs/ and the error messages share one source.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, TypeAlias

from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model, model_validator

from service.errors import InputError
from service.physics.analog import AnalogSensor
from service.physics.effects import EFFECTS_BY_KIND
from service.physics.rotation_axis import RotationBench
from service.physics.stage import StageBench
from service.physics.turntable import TurntableInclinometer

if TYPE_CHECKING:
    from pydantic_core import ErrorDetails

PRESET_DIR = Path(__file__).parent / "presets"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)


def _effects_model(kind: str) -> type[BaseModel]:
    fields: dict[str, Any] = {}
    for eff in EFFECTS_BY_KIND[kind].values():
        pf: dict[str, Any] = {}
        for param in eff.params:
            if param.is_bool:
                pf[param.name] = (bool, Field(param.default, description=param.doc or param.unit))
            else:
                desc = f"[{param.unit}] {param.doc}".strip()
                pf[param.name] = (
                    float,
                    Field(
                        param.default,
                        ge=param.lo,
                        le=param.hi,
                        description=desc,
                        allow_inf_nan=False,
                    ),
                )
        m = create_model(
            f"{kind.title()}_{eff.name}", __config__=ConfigDict(extra="forbid", strict=True), **pf
        )
        m.__doc__ = eff.doc
        fields[eff.name] = (m | None, Field(None, description=eff.doc))
    model = create_model(
        f"{kind.title()}Effects", __config__=ConfigDict(extra="forbid", strict=True), **fields
    )
    model.__doc__ = (
        f"Effects of a {kind} bench; an effect is on when it is named "
        "(offaxis_coupling is on unless disabled)."
    )
    return model


def hardware_model(name: str, hardware: type, **run_fields: Any) -> type[BaseModel]:
    """A scenario's `bench` section as a strict model of a physics hardware dataclass.

    Field names, types, defaults and bounds (the fields' metadata) are the dataclass's own, so the
    hardware is defined once, in service.physics; `run_fields` adds what a scenario says about the
    run rather than the hardware.
    """
    hints = typing.get_type_hints(hardware)
    fields: dict[str, Any] = {}
    for hardware_field in dataclasses.fields(hardware):
        meta = dict(hardware_field.metadata)
        typ: Any = hints[hardware_field.name]
        if "choices" in meta:
            typ = Literal[tuple(meta.pop("choices"))]
        default = (
            hardware_field.default
            if hardware_field.default is not dataclasses.MISSING
            else meta.pop("default", ...)
        )
        meta.pop("default", None)
        fields[hardware_field.name] = (Annotated[typ, Field(**meta)] if meta else typ, default)
    return create_model(name, __base__=_Strict, **fields, **run_fields)


if TYPE_CHECKING:  # built at import time from the registries; a type checker sees them as any model
    StageEffects: TypeAlias = Any
    RotationEffects: TypeAlias = Any
    ScaleEffects: TypeAlias = Any
    TurntableEffects: TypeAlias = Any
    StageBenchSpec: TypeAlias = Any
    RotationBenchSpec: TypeAlias = Any
    ScaleBenchSpec: TypeAlias = Any
    TurntableBenchSpec: TypeAlias = Any
else:
    StageEffects = _effects_model("stage")
    RotationEffects = _effects_model("rotation")
    ScaleEffects = _effects_model("scale")
    TurntableEffects = _effects_model("turntable")

Finite = Annotated[float, Field(allow_inf_nan=False)]
MAX_AXIS_VALUES = 100_000  # values of one grid axis
# rows of a simulated dataset: far beyond any bench run, and still a file of tens of MB
MAX_ROWS = 1_000_000


class AxisRange(_Strict):
    """Evenly spaced values from start to stop inclusive, by step or by count."""

    start: Finite
    stop: Finite
    step: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    count: Annotated[int, Field(ge=1, le=MAX_AXIS_VALUES)] | None = None

    @model_validator(mode="after")
    def _one_of(self) -> AxisRange:
        if (self.step is None) == (self.count is None):
            raise ValueError("give exactly one of step or count")
        if self.step is not None and abs(self.stop - self.start) / self.step + 1 > MAX_AXIS_VALUES:
            raise ValueError(
                f"step {self.step:g} from {self.start:g} to {self.stop:g} gives more than "
                f"{MAX_AXIS_VALUES:,} values"
            )
        return self

    def size(self) -> int:
        if self.count is not None:
            return self.count
        assert self.step is not None  # the validator requires exactly one of them
        return int(round(abs(self.stop - self.start) / self.step)) + 1

    def values(self) -> list[float]:
        import numpy as np

        if self.count is not None:
            return [float(value) for value in np.linspace(self.start, self.stop, self.count)]
        assert self.step is not None
        sign = 1.0 if self.stop >= self.start else -1.0
        return [float(self.start + sign * i * self.step) for i in range(self.size())]


Axis = Annotated[list[Finite], Field(min_length=1, max_length=MAX_AXIS_VALUES)] | AxisRange


def axis_values(a: list[float] | AxisRange) -> list[float]:
    return a.values() if isinstance(a, AxisRange) else list(a)


def axis_size(a: list[float] | AxisRange) -> int:
    return a.size() if isinstance(a, AxisRange) else len(a)


def _rows(sc: Scenario) -> tuple[int, str]:
    """Rows the scenario would simulate, and the grid fields that set them."""
    if isinstance(sc, StageScenario):
        grid = sc.grid
        return (
            axis_size(grid.x_deg) * axis_size(grid.y_deg) * grid.repeats * grid.readings_per_stand,
            "grid.x_deg × grid.y_deg × grid.repeats × grid.readings_per_stand",
        )
    if isinstance(sc, RotationScenario):
        return axis_size(sc.grid.theta_deg) * sc.grid.repeats, "grid.theta_deg × grid.repeats"
    if isinstance(sc, ScaleScenario):
        return axis_size(sc.grid.ref_arcsec) * sc.grid.repeats, "grid.ref_arcsec × grid.repeats"
    return axis_size(sc.grid.azimuth_deg) * len(sc.grid.cycles), "grid.azimuth_deg × grid.cycles"


class Environment(_Strict):
    """Sensor temperature during the run: start + rate * t + amplitude * sin(2π t / period)."""

    temp_c: Annotated[float, Field(ge=-50, le=150)] = 20.0
    temp_rate_c_per_h: Annotated[float, Field(ge=-20, le=20)] = 0.0
    temp_amp_c: Annotated[float, Field(ge=0, le=50)] = 0.0
    temp_period_h: Annotated[float, Field(gt=0, le=1000)] = 24.0


if not TYPE_CHECKING:
    StageBenchSpec = hardware_model("StageBenchSpec", StageBench)


class StageGrid(_Strict):
    """Commanded stage points; every (x, y) combination, visited in the given order.

    Each visit is one move (one draw of the stage's positioning error); `readings_per_stand`
    rows are read while the stage stands there, sharing that draw, each with its own sensor noise.
    """

    x_deg: Axis
    y_deg: Axis
    repeats: Annotated[int, Field(ge=1, le=1000)] = 1
    order: Literal["serpentine", "raster", "random"] = "serpentine"
    settle_s: Annotated[float, Field(ge=0, le=3600)] = 10.0
    readings_per_stand: Annotated[
        int,
        Field(
            ge=1,
            le=1000,
            description="rows read at each stand of the stage (one move): they share the stage's "
            "positioning error, each has its own reading noise",
        ),
    ] = 1
    reading_interval_s: Annotated[
        float, Field(gt=0, le=3600, description="time between the readings at one stand (seconds)")
    ] = 1.0


class _ScenarioBase(_Strict):
    name: str = "custom"
    description: str = ""
    seed: Annotated[int, Field(ge=0)] = 0


class StageScenario(_ScenarioBase):
    kind: Literal["stage"]
    bench: StageBenchSpec = StageBenchSpec()
    effects: StageEffects = Field(default_factory=StageEffects)
    grid: StageGrid
    environment: Environment = Environment()
    controller_homed: bool = Field(
        True,
        description="whether the stage controller has found its reference switches when the "
        "simulated bench "
        "starts; false: as after power-up, it refuses moves ('not homed') until it is homed",
    )


if not TYPE_CHECKING:
    RotationBenchSpec = hardware_model("RotationBenchSpec", RotationBench)


class RotationGrid(_Strict):
    theta_deg: Axis
    repeats: Annotated[int, Field(ge=1, le=1000)] = 1


class RotationScenario(_ScenarioBase):
    kind: Literal["rotation"]
    bench: RotationBenchSpec
    effects: RotationEffects = Field(default_factory=RotationEffects)
    grid: RotationGrid


if not TYPE_CHECKING:
    ScaleBenchSpec = hardware_model(
        "ScaleBenchSpec",
        AnalogSensor,
        # where the run starts, not hardware
        start_arcsec=(Annotated[float, Field(ge=-18_000, le=18_000)], -1780.0),
    )


class ScaleGrid(_Strict):
    ref_arcsec: Axis
    repeats: Annotated[int, Field(ge=1, le=1000)] = 1


class ScaleScenario(_ScenarioBase):
    kind: Literal["scale"]
    bench: ScaleBenchSpec = ScaleBenchSpec()
    effects: ScaleEffects = Field(default_factory=ScaleEffects)
    grid: ScaleGrid
    environment: Environment = Environment()


if not TYPE_CHECKING:
    TurntableBenchSpec = hardware_model(
        "TurntableBenchSpec",
        TurntableInclinometer,
        # the run's pair geometry, not the sensor
        rotation_deg=(Annotated[float, Field(ge=90, le=270)], 180.0),
        reading_unit=(str, "mrad"),
    )


class AxisTilt(_Strict):
    north_arcsec: Annotated[float, Field(ge=-3600, le=3600)]
    east_arcsec: Annotated[float, Field(ge=-3600, le=3600)]


class TurntableGrid(_Strict):
    """Each cycle is one levelling of the instrument (one axis tilt) read at every azimuth."""

    azimuth_deg: Axis
    cycles: Annotated[list[AxisTilt], Field(min_length=1, max_length=10_000)]
    pair_interval_s: Annotated[float, Field(ge=0, le=3600)] = 120.0


class TurntableScenario(_ScenarioBase):
    kind: Literal["turntable"]
    bench: TurntableBenchSpec
    effects: TurntableEffects = Field(default_factory=TurntableEffects)
    grid: TurntableGrid


class ScenarioFile(BaseModel):
    """A tiltlab scenario (one of four kinds, told apart by `kind`)."""

    model_config = ConfigDict(title="tiltlab scenario")
    root: Annotated[
        StageScenario | RotationScenario | ScaleScenario | TurntableScenario,
        Field(discriminator="kind"),
    ]


Scenario = StageScenario | RotationScenario | ScaleScenario | TurntableScenario


def effects_dict(scenario: Scenario) -> dict[str, dict[str, float]]:
    """The effects the scenario names, with every parameter filled in (a switch's bool is a number
    too)."""
    return {name: dict(val) for name, val in scenario.effects.model_dump(exclude_none=True).items()}


def _union_tag(x: str) -> bool:
    return x[:1].isupper() or x.startswith("list[") or x.startswith("function-")


def _format_error(source: str, err: ValidationError) -> str:
    errors = err.errors()
    # For a union (a list or a range), the branch whose shape matched says the useful thing.
    errors.sort(
        key=lambda e: e["type"].endswith("_type") and any(_union_tag(str(x)) for x in e["loc"])
    )
    first = errors[0]
    loc = _field_path(first)
    field = ".".join(loc) or "(top level)"
    msg = _problem(first, loc)
    more = len(err.errors()) - 1
    return f"{source}: field {field}: {msg}" + (
        f" (and {more} more problem{'s' * (more > 1)})" if more else ""
    )


def _field_path(error: ErrorDetails) -> list[str]:
    """The scenario fields an error is about, without the wrapper's root and pydantic's
    union-branch tags."""
    loc = [str(x) for x in error["loc"]]
    if loc and loc[0] == "root":
        loc = loc[1:]
    # drop pydantic's union-branch tags ("stage", "AxisRange", "list[...]") from the path
    return [
        x for x in loc if x not in ("stage", "rotation", "scale", "turntable") and not _union_tag(x)
    ]


def _problem(error: ErrorDetails, loc: list[str]) -> str:
    """What is wrong, in the scenario's words: an unknown effect or field, a missing one, or
    pydantic's message with the value given."""
    msg = error["msg"].removeprefix("Value error, ")
    if error["type"] == "extra_forbidden":
        parent = ".".join(loc[:-1])
        if parent == "effects":
            msg = f"unknown effect {loc[-1]!r}"
        else:
            msg = f"unknown field {loc[-1]!r}"
    elif error["type"] == "missing":
        msg = "missing required field"
    elif "input" in error and not isinstance(error["input"], (dict, list)):
        msg = f"{msg} (got {error['input']!r})"
    return msg


def parse_scenario(data: Any, source: str = "scenario") -> Scenario:
    if not isinstance(data, dict):
        raise InputError(f"{source}: a scenario is a JSON object, not {type(data).__name__}")
    if "kind" not in data:
        raise InputError(
            f"{source}: field kind: missing required field (one of stage, rotation, scale, "
            "turntable)"
        )
    if data.get("kind") not in ("stage", "rotation", "scale", "turntable"):
        raise InputError(
            f"{source}: field kind: {data.get('kind')!r} is not one of stage, rotation, scale, "
            "turntable"
        )
    try:
        sc = ScenarioFile.model_validate({"root": data}).root
    except ValidationError as err:
        raise InputError(_format_error(source, err)) from None
    n, fields = _rows(sc)
    if n > MAX_ROWS:
        raise InputError(
            f"{source}: field grid: {fields} gives {n:,} rows, more than the {MAX_ROWS:,} "
            "a scenario may simulate"
        )
    if isinstance(sc, StageScenario):
        travel = sc.bench.travel_deg
        for ax in ("x_deg", "y_deg"):
            vals = axis_values(getattr(sc.grid, ax))
            worst = max(abs(value) for value in vals)
            if worst > travel + 1e-9:
                raise InputError(
                    f"{source}: field grid.{ax}: {worst:g} deg is beyond the stage travel of "
                    f"±{travel:g} deg"
                )
    return sc


def preset_names() -> list[str]:
    return sorted(path.stem for path in PRESET_DIR.glob("*.json"))


def scenario_data(name_or_path: str | Path) -> tuple[object, str]:
    """The raw JSON of a preset (by name) or a scenario file (an object if it is a scenario: as
    parse_scenario checks), and where it came from."""
    path = Path(name_or_path)
    if not path.suffix and (PRESET_DIR / f"{path.name}.json").exists() and not path.exists():
        path = PRESET_DIR / f"{path.name}.json"
    elif not path.exists():
        raise InputError(
            f"scenario {str(name_or_path)!r}: no such preset or file (presets: "
            f"{', '.join(preset_names())})"
        )
    try:
        # a byte-order mark from an editor is harmless
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except json.JSONDecodeError as exc:
        raise InputError(
            f"{path}: not valid JSON: line {exc.lineno} column {exc.colno}: {exc.msg}"
        ) from None
    except RecursionError:
        raise InputError(f"{path}: not a scenario: JSON nested too deeply") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read: {exc}") from None
    return data, str(path)


def load_scenario(name_or_path: str | Path) -> Scenario:
    """A preset by name, or a scenario JSON file, validated."""
    data, source = scenario_data(name_or_path)
    return parse_scenario(data, source=source)


def json_schema() -> dict[str, object]:
    """docs/scenario.schema.json: the JSON Schema of a scenario file."""
    generated = ScenarioFile.model_json_schema()
    schema: dict[str, object] = generated
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["$id"] = "https://tiltlab.example/schemas/scenario.schema.json"
    # the file is the scenario object itself, not the wrapper
    root: dict[str, object] = generated["properties"]["root"]
    schema.pop("properties", None)
    schema.pop("required", None)
    schema.update({key: value for key, value in root.items() if key != "title"})
    schema["description"] = (
        "A tiltlab scenario: bench parameters, per-effect magnitudes (names of docs/models.md "
        "§5 with units in the parameter names or descriptions), the point grid, environment and "
        "random seed."
    )
    return schema
