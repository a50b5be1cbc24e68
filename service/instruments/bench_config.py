"""Bench configuration files (TOML): which instrument plays which role on which port.

One file may describe several benches. Each bench has a kind (`stage`: two stacked swing
stages carrying a reference and a measurement sensor, optionally an ADC-read analog
sensor; `rotary`: a rotary table carrying a triaxial module or an RS-485 inclinometer),
the fixed hardware of its stages, and one table per role:

    [benches.stage-1]
    kind = "stage"

    [benches.stage-1.hardware]          # the stacked stages (defaults: the seed 000 bench)
    upper_gear_ratio = 320
    lower_gear_ratio = 450
    step_angle_deg = 1.8
    microsteps = 8
    travel_deg = 15
    meas_flip = "none"                  # measurement sensor mounted upside down about "x" or "y"

    [benches.stage-1.roles.reference_sensor]
    port = "/dev/ttyUSB0"               # or socket://host:port, rfc2217://host:port
    address = 0

    [benches.stage-1.roles.measurement_sensor]
    usb_serial = "FT5XYZ12"             # found by the USB adapter's serial number instead of a path

    [benches.stage-1.roles.stage]
    port = "/dev/ttyUSB2"

    [benches.stage-1.roles.ambient_sensor]   # optional: the laboratory's air, temperature, humidity
    port = "/dev/ttyUSB3"
    address = "01"
    standard_uncertainty_c = 0.1             # as the thermo-hygrometer's certificate states them
    standard_uncertainty_pct = 2.0

The hardware table is the same model as a scenario file's `bench` section, so the
kinematic model, the simulator and the daemon read one definition. Every problem is an
InputError of one line naming the file and the field.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from service.errors import InputError
from service.physics.stage import StageBench
from service.scenarios.model import StageBenchSpec

ROLES = (
    "reference_sensor",
    "measurement_sensor",
    "stage",
    "adc_sensor",
    "rotary_table",
    "triaxial_sensor",
    "turntable_sensor",
    "ambient_sensor",
)
# The byte protocol of each role's instrument family (A binary frames, B RS-485 ASCII, C ADC, D
# controller).
PROTOCOL_OF_ROLE = {
    "reference_sensor": "binary",
    "measurement_sensor": "binary",
    "triaxial_sensor": "binary",
    "turntable_sensor": "rs485",
    "adc_sensor": "adc",
    "ambient_sensor": "rs485",
    "stage": "controller",
    "rotary_table": "controller",
}
DEFAULT_BAUD = {"binary": 9600, "rs485": 115200, "adc": 9600, "controller": 57600}
BAUD_RATES = (2400, 4800, 9600, 19200, 38400, 57600, 115200)
# Family (A) automatic output: 0 answers requests only; "continuous" sends frames back to back.
OUTPUT_RATES_HZ = (0, 5, 15, 25, 35, 50, 100)

REQUIRED_ROLES = {
    "stage": ("reference_sensor", "measurement_sensor", "stage"),
    "rotary": ("rotary_table",),
}
OPTIONAL_ROLES = {
    "stage": ("adc_sensor", "ambient_sensor"),
    "rotary": ("triaxial_sensor", "turntable_sensor", "ambient_sensor"),
}


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)


class PortRole(_Strict):
    """Where an instrument is plugged in, and how long a request may wait for its answer."""

    port: Annotated[str, Field(min_length=1, max_length=200)] | None = None
    usb_serial: Annotated[str, Field(min_length=1, max_length=100)] | None = None
    baud: int | None = None
    timeout_s: Annotated[float, Field(gt=0, le=60)] = 0.5

    @model_validator(mode="after")
    def _one_place(self) -> PortRole:
        if (self.port is None) == (self.usb_serial is None):
            raise ValueError(
                "give exactly one of port (a path, socket:// or rfc2217:// URL) or usb_serial"
            )
        if self.baud is not None and self.baud not in BAUD_RATES:
            raise ValueError(f"baud {self.baud} is not one of {', '.join(map(str, BAUD_RATES))}")
        return self

    @property
    def where(self) -> str:
        """The port as a person would name it in a message."""
        return self.port if self.port is not None else f"usb_serial={self.usb_serial}"


class BinaryInclinometerRole(PortRole):
    """Family (A): biaxial inclinometer (or the triaxial module) with 0x68 frames."""

    address: Annotated[int, Field(ge=0, le=255)] = 0
    output_rate_hz: int | Literal["continuous"] = 50
    resolution_deg: Annotated[float, Field(gt=0, le=1)] = 0.0001

    @model_validator(mode="after")
    def _rate(self) -> BinaryInclinometerRole:
        if self.output_rate_hz != "continuous" and self.output_rate_hz not in OUTPUT_RATES_HZ:
            raise ValueError(
                f"output_rate_hz {self.output_rate_hz!r} is not one of "
                f'{", ".join(map(str, OUTPUT_RATES_HZ))} or "continuous"'
            )
        return self


class Rs485InclinometerRole(PortRole):
    """Family (B): addressable RS-485 inclinometer; several may share one port."""

    address: Annotated[str, Field(pattern=r"^[0-9A-Fa-f]{2}$")] = "01"
    poll_rate_hz: Annotated[float, Field(gt=0, le=200)] = 10.0


class AmbientSensorRole(PortRole):
    """Family (B) thermo-hygrometer reading the laboratory's air (command TH); the standard
    uncertainties of its temperature and humidity as its calibration certificate states them enter
    the conditions a job records."""

    address: Annotated[str, Field(pattern=r"^[0-9A-Fa-f]{2}$")] = "01"
    poll_rate_hz: Annotated[float, Field(gt=0, le=10)] = 1.0
    standard_uncertainty_c: Annotated[float, Field(gt=0, le=10)] = 0.1
    standard_uncertainty_pct: Annotated[float, Field(gt=0, le=50)] = 2.0


class AdcRole(PortRole):
    """Family (C): analog tilt sensor behind a 12-bit ADC (0-5 V in 4096 counts)."""

    conversions_per_reading: Annotated[int, Field(ge=1, le=1000)] = 10
    poll_rate_hz: Annotated[float, Field(gt=0, le=50)] = 5.0


class StageControllerRole(PortRole):
    """Family (D) driving the stacked stages: axis 1 upper (x), axis 2 lower (y).

    Pulse equivalents come from the bench's hardware table; soft limits default to its travel.
    """

    velocity_pulses_per_s: Annotated[int, Field(ge=1, le=1_000_000)] = 4000
    soft_limits_x_deg: Annotated[list[float], Field(min_length=2, max_length=2)] | None = None
    soft_limits_y_deg: Annotated[list[float], Field(min_length=2, max_length=2)] | None = None
    poll_rate_hz: Annotated[float, Field(gt=0, le=100)] = 10.0


class RotaryTableRole(PortRole):
    """Family (D) axis that turns the rotary table without limit."""

    axis: Annotated[int, Field(ge=1, le=9)] = 3
    pulse_deg: Annotated[float, Field(gt=0, le=10)] = 0.001
    velocity_pulses_per_s: Annotated[int, Field(ge=1, le=1_000_000)] = 20_000
    poll_rate_hz: Annotated[float, Field(gt=0, le=100)] = 10.0


ROLE_MODELS: dict[str, type[PortRole]] = {
    "reference_sensor": BinaryInclinometerRole,
    "measurement_sensor": BinaryInclinometerRole,
    "triaxial_sensor": BinaryInclinometerRole,
    "turntable_sensor": Rs485InclinometerRole,
    "adc_sensor": AdcRole,
    "ambient_sensor": AmbientSensorRole,
    "stage": StageControllerRole,
    "rotary_table": RotaryTableRole,
}


class BenchConfig(_Strict):
    name: str = ""
    kind: Literal["stage", "rotary"]
    description: str = ""
    hardware: StageBenchSpec | None = None
    # Each role's table as the file has it (any TOML values): validated as its role's model into
    # `role_specs`, where the keys each role takes are named.
    roles: dict[str, dict[str, object]]
    # Filled by validation: each role's table as its typed model.
    role_specs: dict[str, PortRole] = Field(default_factory=dict, exclude=True)

    @model_validator(mode="after")
    def _roles(self) -> BenchConfig:
        self._check_role_names()
        if self.kind == "rotary" and self.hardware is not None:
            raise ValueError("hardware: describes stacked swing stages; a rotary bench has none")
        if self.kind == "stage" and self.hardware is None:
            self.hardware = StageBenchSpec()
        self.role_specs = self._typed_roles()
        if self.kind == "stage":
            self._check_soft_limits()
        return self

    def _check_role_names(self) -> None:
        """Every role known and one this kind of bench has; every role it needs present."""
        allowed = REQUIRED_ROLES[self.kind] + OPTIONAL_ROLES[self.kind]
        for role in self.roles:
            if role not in ROLES:
                raise ValueError(f"roles.{role}: unknown role; roles are {', '.join(ROLES)}")
            if role not in allowed:
                raise ValueError(
                    f"roles.{role}: a {self.kind} bench has the roles {', '.join(allowed)}"
                )
        for role in REQUIRED_ROLES[self.kind]:
            if role not in self.roles:
                raise ValueError(
                    f"roles.{role}: missing; a {self.kind} bench needs "
                    f"{', '.join(REQUIRED_ROLES[self.kind])}"
                )
        if self.kind == "rotary" and not any(
            optional_role in self.roles for optional_role in OPTIONAL_ROLES["rotary"]
        ):
            raise ValueError("roles: a rotary bench needs a triaxial_sensor or a turntable_sensor")

    def _typed_roles(self) -> dict[str, PortRole]:
        """Each role's table validated as its own model; the first problem names the role."""
        specs: dict[str, PortRole] = {}
        for role, table in self.roles.items():
            try:
                specs[role] = ROLE_MODELS[role].model_validate(table)
            except ValidationError as exc:
                problem = _first(exc)
                raise ValueError(
                    f"roles.{role}{'.' if ': ' in problem else ': '}{problem}"
                ) from None
        return specs

    def _check_soft_limits(self) -> None:
        stage = self.role_specs["stage"]
        assert isinstance(stage, StageControllerRole) and self.hardware is not None
        travel = self.hardware.travel_deg
        for axis in ("x", "y"):
            limits = getattr(stage, f"soft_limits_{axis}_deg")
            if limits is not None and not (-travel <= limits[0] < limits[1] <= travel):
                raise ValueError(
                    f"roles.stage.soft_limits_{axis}_deg: {list(limits)} must be [low, high] "
                    f"with low < high within the travel of ±{travel:g} deg"
                )

    def role(self, role: str) -> PortRole:
        return self.role_specs[role]

    def stage_rates_deg_per_s(self) -> tuple[float, float]:
        """How fast each of the stacked stages tilts the table (x, y): the controller's velocity on
        each stage's pulse equivalent (a move of both waits for the slower)."""
        stage = self.role("stage")
        assert isinstance(stage, StageControllerRole)
        bench = self.stage_bench()
        return (
            stage.velocity_pulses_per_s * bench.pulse_x_deg,
            stage.velocity_pulses_per_s * bench.pulse_y_deg,
        )

    def stage_bench(self) -> StageBench:
        """The stacked stages' hardware as the physics and calibration code take it."""
        if self.hardware is None:
            raise InputError(
                f"bench {self.name!r} is a {self.kind} bench: it has no stacked stages"
            )
        return StageBench(**self.hardware.model_dump())


class BenchesFile(_Strict):
    benches: dict[str, BenchConfig]
    # Written by `tiltlab sim`: the simulated bench runs this many times faster than real time.
    sim_speed: Annotated[float, Field(gt=0, le=10_000)] | None = None

    @model_validator(mode="after")
    def _names(self) -> BenchesFile:
        if not self.benches:
            raise ValueError("benches: the file names no bench")
        for name, bench in self.benches.items():
            bench.name = name
        self._check_shared_ports()
        return self

    def _check_shared_ports(self) -> None:
        """One port may carry several RS-485 instruments (by address), nothing else."""
        users: dict[str, list[tuple[str, str, PortRole]]] = {}
        for bname, bench in self.benches.items():
            for role, spec in bench.role_specs.items():
                users.setdefault(spec.where, []).append((bname, role, spec))
        for where, on_port in users.items():
            if len(on_port) >= 2:
                _check_bus(where, on_port)

    def bench(self, name: str | None = None) -> BenchConfig:
        """A bench by name; without a name, the file's only bench."""
        if name is None:
            if len(self.benches) != 1:
                raise InputError(
                    f"the configuration describes {len(self.benches)} benches "
                    f"({', '.join(self.benches)}); name one"
                )
            return next(iter(self.benches.values()))
        if name not in self.benches:
            raise InputError(
                f"no bench named {name!r}; the configuration has {', '.join(self.benches)}"
            )
        return self.benches[name]


def _check_bus(where: str, on_port: list[tuple[str, str, PortRole]]) -> None:
    """The instruments given one port (bench, role, spec): RS-485 ones only, each at its own
    address, all at one baud rate."""
    names = ", ".join(f"{bench_name}.{role}" for bench_name, role, _ in on_port)
    if any(
        not isinstance(spec, Rs485InclinometerRole | AmbientSensorRole) for _, _, spec in on_port
    ):
        raise ValueError(
            f"port {where} is given to {names}; only RS-485 instruments may share a port"
        )
    addresses = [
        spec.address.upper()
        for _, _, spec in on_port
        if isinstance(spec, Rs485InclinometerRole | AmbientSensorRole)
    ]
    if len(set(addresses)) != len(addresses):
        raise ValueError(
            f"port {where}: {names} share an address; each instrument on a bus needs its own"
        )
    if len({spec.baud for _, _, spec in on_port}) > 1:
        raise ValueError(f"port {where}: {names} give different baud rates for one bus")


def _first(exc: ValidationError) -> str:
    """The first problem as `field.path: message` (or the message alone when it is about the whole
    table)."""
    error = exc.errors()[0]
    loc = ".".join(str(x) for x in error["loc"] if not str(x).startswith("function-"))
    msg = error["msg"].removeprefix("Value error, ")
    if error["type"] == "extra_forbidden":
        msg = "unknown field"
    elif error["type"] == "missing":
        msg = "missing required field"
    elif "input" in error and not isinstance(error["input"], dict | list):
        msg = f"{msg} (got {error['input']!r})"
    return f"{loc}: {msg}" if loc else msg


def parse_bench_config(data: object, source: str = "bench configuration") -> BenchesFile:
    if not isinstance(data, dict):
        raise InputError(f"{source}: a bench configuration is a TOML table")
    try:
        return BenchesFile.model_validate(data)
    except ValidationError as exc:
        raise InputError(f"{source}: {_first(exc)}") from None


def load_bench_config(path: str | Path) -> BenchesFile:
    config_path = Path(path).expanduser()
    try:
        data = tomllib.loads(config_path.read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise InputError(f"{config_path}: no such bench configuration file") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{config_path}: not valid TOML: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{config_path}: cannot read: {exc}") from None
    return parse_bench_config(data, source=str(config_path))


def load_stage_bench(path: str | Path) -> tuple[StageBench, str]:
    """The stacked stages' hardware from a bench configuration (TOML) or a scenario file's `bench`
    section (JSON).

    Returns the bench and where it came from, as MODEL.json and the reports record it. A
    configuration with several stage benches is refused: name the file of the one the data came
    from.
    """
    bench_path = Path(path).expanduser()
    if bench_path.suffix.lower() == ".toml":
        benches = [
            bench
            for bench in load_bench_config(bench_path).benches.values()
            if bench.kind == "stage"
        ]
        if len(benches) != 1:
            names = ", ".join(bench.name for bench in benches) or "none"
            raise InputError(
                f"{bench_path}: --bench needs a configuration with one stage bench, this one has "
                f"{len(benches)} ({names})"
            )
        return benches[0].stage_bench(), f"{bench_path} (bench {benches[0].name!r}, hardware table)"
    if bench_path.suffix.lower() == ".json":
        from service.scenarios.model import StageScenario, load_scenario

        if not bench_path.is_file():
            raise InputError(f"{bench_path}: no such scenario file")
        scenario = load_scenario(bench_path)
        if not isinstance(scenario, StageScenario):
            raise InputError(
                f"{bench_path}: a {scenario.kind} scenario has no stacked stages; --bench needs a "
                "stage bench"
            )
        return StageBench(**scenario.bench.model_dump()), f"{bench_path} (scenario's bench section)"
    raise InputError(
        f"{bench_path}: --bench takes a bench configuration (.toml) or a scenario file (.json)"
    )
