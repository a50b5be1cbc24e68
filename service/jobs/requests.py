"""The body of POST /calibrations and its checks (a bad grid is refused before anything starts)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    GetJsonSchemaHandler,
    Strict,
    model_validator,
)
from pydantic.config import JsonDict
from pydantic.json_schema import JsonSchemaValue

from service.errors import InputError

PROCEDURES = ("stage-grid", "scale", "rotation", "turntable")
KIND_OF_PROCEDURE = {
    "stage-grid": "stage",
    "scale": "scale",
    "rotation": "rotation",
    "turntable": "turntable",
}
# The fewest fit points each stage method needs (parameters it determines, with one spare).
MIN_POINTS = {"kinematic": 6, "homography": 5, "axis-transform": 4, "coupling": 3}


class RequestProblem(InputError):
    """A request that cannot be used; `field` names what was wrong (422, or 409 for a conflict)."""

    def __init__(self, field: str, message: str, status: int = 422) -> None:
        super().__init__(f"{field}: {message}")
        self.field, self.status = field, status


# Ids are INTEGER columns: 32-bit on PostgreSQL, the narrower of the two databases.
DB_ID_MAX = 2**31 - 1
# Control characters (tabs and line breaks aside) and the Unicode bidirectional embeddings,
# overrides and isolates, which make text display in another order than it was typed ("Trojan
# Source"): a certificate or a record must read as it was written.
# as regex escapes
CONTROL_CHARACTERS = r"\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069"
_CONTROL = re.compile(f"[{CONTROL_CHARACTERS}]")
TEXT_PATTERN = f"^[^{CONTROL_CHARACTERS}]*$"  # the rule as the OpenAPI document states it
_BIDI = re.compile(r"[\u202a-\u202e\u2066-\u2069]")


def _printable(text: str) -> str:
    """Text as a lab person typed it: tabs and line breaks, but no NUL or other control character
    (PostgreSQL refuses NUL, and a certificate cannot carry one), and no bidirectional override."""
    found = _CONTROL.search(text)
    if found:
        what = (
            "bidirectional control character" if _BIDI.match(found.group()) else "control character"
        )
        raise ValueError(
            f"{what} U+{ord(found.group()):04X} at position {found.start()}; text must be printable"
            " and read in the order it was typed"
        )
    return text


# Request field types: a number is a finite JSON number (not a boolean, NaN or an infinity), a count
# an integer (not a boolean), an id one the database can hold, text free of control characters.
def _whole(value: object) -> object:
    """A count as JSON may write it: 18 or 18.0 (JSON Schema's integers are the numbers without a
    fraction); never true/false, never 18.5."""
    if isinstance(value, float) and value.is_integer() and abs(value) < 2**53:
        return int(value)
    return value


Finite = Annotated[float, Strict(), Field(allow_inf_nan=False)]
Count = Annotated[int, BeforeValidator(_whole), Strict()]
DbId = Annotated[int, BeforeValidator(_whole), Strict(), Field(ge=1, le=DB_ID_MAX)]


@dataclass(frozen=True)
class _StatedPattern:
    """States a text rule in the JSON Schema as a pattern (checked by a validator of its own, whose
    message says where)."""

    pattern: str = TEXT_PATTERN

    def __get_pydantic_json_schema__(
        self, core_schema: Any, handler: GetJsonSchemaHandler
    ) -> JsonSchemaValue:
        schema = handler(core_schema)
        schema["pattern"] = self.pattern
        return schema


Text = Annotated[str, AfterValidator(_printable), _StatedPattern()]
# One line that says something (a person's name or function): no control character at all, tab and
# line breaks included, and not only blanks, as service.storage.tokens checks it
_LINE_CONTROL = CONTROL_CHARACTERS + r"\x09\x0a\x0d"
# (the lookahead: a pattern's "$" in Python also matches before a final line break)
LINE_PATTERN = f"^(?!.*\\n)[^{_LINE_CONTROL}]*[^\\s{_LINE_CONTROL}][^{_LINE_CONTROL}]*$"
Line = Annotated[str, AfterValidator(_printable), _StatedPattern(LINE_PATTERN)]


class RequestBody(BaseModel):
    """A request body: unknown fields refused, numbers finite."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class Settle(RequestBody):
    tolerance_deg: Annotated[Finite, Field(gt=0, le=1.0)] = 0.002
    window_s: Annotated[Finite, Field(gt=0, le=600)] = 0.5
    timeout_s: Annotated[Finite, Field(gt=0, le=3600)] = 30.0


class Validation(RequestBody):
    n_points: Annotated[Count, Field(ge=0, le=1000)] = 4


class Grid(RequestBody):
    """Either a rectangle `x_deg`, `y_deg`, `n_x`, `n_y` or explicit `points`."""

    x_deg: Annotated[list[Finite], Field(min_length=2, max_length=2)] | None = None
    y_deg: Annotated[list[Finite], Field(min_length=2, max_length=2)] | None = None
    n_x: Annotated[Count, Field(ge=1, le=1000)] | None = None
    n_y: Annotated[Count, Field(ge=1, le=1000)] | None = None
    points: (
        Annotated[
            list[Annotated[list[Finite], Field(min_length=2, max_length=2)]],
            Field(max_length=100_000),
        ]
        | None
    ) = None
    # scale (stage x angles) and rotation (rotary table angles): the procedure's own points
    angles_deg: Annotated[list[Finite], Field(min_length=1, max_length=100_000)] | None = None
    range_deg: Annotated[list[Finite], Field(min_length=2, max_length=2)] | None = None
    n: Annotated[Count, Field(ge=1, le=100_000)] | None = None

    def size(self) -> int:
        """How many points the grid has, counted without making them."""
        if self.points is not None:
            return len(self.points)
        if self.angles_deg is not None:
            return len(self.angles_deg)
        if self.n is not None:
            return self.n
        return (self.n_x or 0) * (self.n_y or 0)

    def angles(self) -> list[float]:
        if self.angles_deg is not None:
            return [float(angle) for angle in self.angles_deg]
        assert self.range_deg is not None and self.n is not None  # checked by the validator
        return [float(angle) for angle in np.linspace(self.range_deg[0], self.range_deg[1], self.n)]

    def is_angles(self) -> bool:
        return self.angles_deg is not None or self.range_deg is not None

    @model_validator(mode="after")
    def _one_form(self) -> Grid:
        if self.angles_deg is not None or self.range_deg is not None or self.n is not None:
            self._check_angles_form()
        else:
            self._check_stage_form()
        return self

    def _check_angles_form(self) -> None:
        """Angles alone (no stage grid beside them): angles_deg, or range_deg and n."""
        if any(
            value is not None for value in (self.x_deg, self.y_deg, self.n_x, self.n_y, self.points)
        ):
            raise ValueError(
                "give either angles (angles_deg, or range_deg and n) or a stage grid, not both"
            )
        if self.angles_deg is None and (self.range_deg is None or self.n is None):
            raise ValueError("angles need angles_deg, or range_deg and n")

    def _check_stage_form(self) -> None:
        """A stage grid in one form: explicit points, or the whole rectangle."""
        rect = [self.x_deg, self.y_deg, self.n_x, self.n_y]
        if self.points is not None and any(value is not None for value in rect):
            raise ValueError("give either points or x_deg, y_deg, n_x, n_y, not both")
        if self.points is None and any(value is None for value in rect):
            raise ValueError("a grid needs x_deg, y_deg, n_x and n_y (or points)")

    def stage_points(self) -> list[tuple[float, float]]:
        if self.points is not None:
            return [(float(x), float(y)) for x, y in self.points]
        # checked by the validator
        assert self.x_deg is not None and self.y_deg is not None and self.n_x and self.n_y
        xs = np.linspace(self.x_deg[0], self.x_deg[1], self.n_x)
        ys = np.linspace(self.y_deg[0], self.y_deg[1], self.n_y)
        # Serpentine order: rows alternate direction, each point still approached from below (see
        # the job).
        return [
            (float(x), float(y)) for j, y in enumerate(ys) for x in (xs if j % 2 == 0 else xs[::-1])
        ]


class AxisReference(RequestBody):
    """turntable: the turntable axis tilt measured independently (e.g. from star observations)."""

    north_arcsec: Finite
    east_arcsec: Finite


class AmbientTemperature(RequestBody):
    value: Annotated[
        Finite, Field(ge=-50, le=100, description="the laboratory's air temperature, °C")
    ]
    standard_uncertainty: Annotated[
        Finite, Field(gt=0, le=10, description="its standard uncertainty u, °C")
    ]


class RelativeHumidity(RequestBody):
    value: Annotated[Finite, Field(ge=0, le=100, description="the air's relative humidity, %")]
    standard_uncertainty: Annotated[
        Finite, Field(gt=0, le=50, description="its standard uncertainty u, %")
    ]


class Conditions(RequestBody):
    """The laboratory's ambient conditions during the job, as read on a calibrated
    thermo-hygrometer."""

    ambient_temperature_c: AmbientTemperature | None = None
    relative_humidity_pct: RelativeHumidity | None = None


def method_per_procedure(schema: JsonDict) -> None:
    """States in the JSON Schema which methods each procedure takes (the request's rule `method` is
    checked by)."""
    from service.calibration.registry import known_methods

    # conditions (JSON Schema's if/then), not alternatives: the body stays one object type for
    # client generators
    schema["allOf"] = [
        {
            "if": {"properties": {"procedure": {"const": procedure}}, "required": ["procedure"]},
            "then": {
                "properties": {"method": {"enum": [*known_methods(KIND_OF_PROCEDURE[procedure])]}}
            },
        }
        for procedure in PROCEDURES
    ]


class CalibrationRequest(RequestBody):
    model_config = ConfigDict(json_schema_extra=method_per_procedure)

    bench: Annotated[Text, Field(max_length=100)] | None = None
    procedure: Literal["stage-grid", "scale", "rotation", "turntable"]
    method: Annotated[Text, Field(max_length=80)]
    grid: Grid | None = None
    samples_per_point: Annotated[Count, Field(ge=1, le=10_000)] = 10
    settle: Settle = Field(default_factory=Settle)
    validation: Validation = Field(default_factory=Validation)
    reference_standards: Annotated[list[DbId], Field(max_length=100)] = Field(
        default_factory=list,
        description="ids of registered reference standards (GET /standards); one past its due"
        " date refuses the job",
    )
    order_id: DbId | None = Field(
        None, description="the LIMS order (POST /orders) this job works on"
    )
    reference: AxisReference | None = None
    conditions: Conditions | None = Field(
        None,
        description="the laboratory's ambient temperature and relative humidity, each with its "
        "standard uncertainty; a bench with an ambient sensor records them itself (its readings "
        "are stated then). Required (the temperature) when the laboratory's settings require "
        "conditions (TILTLAB_REQUIRE_CONDITIONS)",
    )
    note: Annotated[Text, Field(max_length=10_000)] | None = None
    design: Literal["grid", "adaptive"] = Field(
        "grid",
        description="grid: every point of `grid`, `samples_per_point` readings each, settled by "
        "`settle`; adaptive (stage-grid): points of the grid's lattice chosen, settled "
        "statistically and read until the expanded uncertainty of the correction over the "
        "grid's range is at most target_expanded_uncertainty_deg",
    )
    target_expanded_uncertainty_deg: Annotated[Finite, Field(gt=0, le=1.0)] | None = Field(
        None,
        description="adaptive design: the expanded uncertainty (k = 2) of the correction over "
        "the range the job must reach (the record's part of a corrected tilt's uncertainty: "
        "parameters, standard, resolution)",
    )

    @model_validator(mode="after")
    def _design(self) -> CalibrationRequest:
        if self.design == "adaptive":
            if self.procedure != "stage-grid":
                raise ValueError("design adaptive is for stage-grid jobs")
            if self.target_expanded_uncertainty_deg is None:
                raise ValueError("design adaptive needs target_expanded_uncertainty_deg")
            if self.grid is not None and (self.grid.x_deg is None or self.grid.n_x is None):
                raise ValueError(
                    "design adaptive needs a rectangle grid (x_deg, y_deg, n_x, n_y): its range "
                    "and the lattice of candidate points"
                )
        elif self.target_expanded_uncertainty_deg is not None:
            raise ValueError("target_expanded_uncertainty_deg is for design adaptive")
        return self
