"""A whole simulated bench on pseudo-terminals: the instruments' firmware speaking their real bytes,
driven by the scenario's physics, behind stable paths a bench configuration can name.

    bench = start_simulated_bench("seed000", "stage", Clock(20))
    devices = open_bench(bench.config, clock)       # the same drivers as on hardware
    bench.faults("stage").disconnect(0.5)           # the back door
    bench.world.pose_deg                            # the simulated truth
    bench.close()
"""

from __future__ import annotations

import math
import shutil
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Literal, Required, TypedDict

from service.clock import Clock
from service.errors import InputError
from service.instruments import binary
from service.instruments.bench_config import BenchConfig, parse_bench_config
from service.instruments.sim.firmware import (
    AdcFirmware,
    BinaryFirmware,
    ControllerFirmware,
    Rs485BusFirmware,
)
from service.instruments.sim.loopback import LoopbackSimPort
from service.instruments.sim.pty import Faults, SimPort
from service.instruments.sim.world import RotaryWorld, StageWorld, rotary_scenarios, stage_scenario
from service.scenarios.model import ScaleScenario, load_scenario

SimTransport = Literal["pty", "loopback"]
PORT_CLASSES: dict[str, type[SimPort]] = {"pty": SimPort, "loopback": LoopbackSimPort}
SIM_BAUD = {"binary": 115200, "rs485": 115200, "adc": 9600, "controller": 57600}
# the simulated sensors' automatic output, as their stored configuration says
DEFAULT_OUTPUT_RATE_HZ = 25
# At most this share of a simulated line is automatic output: the rest is left for the answers to
# requests (temperatures, zeroing), as a lab would leave a real line headroom.
LINE_SHARE = 0.8
# The lines that carry automatic output on each kind of simulated bench: (role, frame bytes).
AUTO_OUTPUT_LINES = {
    "stage": (("measurement_sensor", 13), ("reference_sensor", 13)),
    "rotary": (("triaxial_sensor", 17),),
}


def fastest_speed(kind: str, output_rate_hz: float = DEFAULT_OUTPUT_RATE_HZ) -> tuple[float, str]:
    """The highest speed-up whose automatic output the simulated lines still carry, and why.

    A sensor sending `output_rate_hz` frames per bench second sends speed times as many per real
    second; its line at SIM_BAUD carries only so many (8N1, ten bits a byte). Beyond that the frames
    would queue without end and the readings arrive ever later.
    """
    limits = []
    for role, frame_bytes in AUTO_OUTPUT_LINES[kind]:
        per_s = 1.0 / binary.frame_time_s(frame_bytes, SIM_BAUD["binary"])
        speed = math.floor(LINE_SHARE * per_s / output_rate_hz)
        limits.append(
            (
                speed,
                (
                    f"the simulated {role} line at {SIM_BAUD['binary']} baud carries {per_s:.0f} "
                    f"frames a second ({LINE_SHARE:.0%} of it, {LINE_SHARE * per_s:.0f}, kept "
                    f"for automatic output), and the sensor sends {output_rate_hz:g} a bench "
                    "second"
                ),
            )
        )
    return min(limits)


class SimulatedBench:
    """Running simulated instruments; `.config` points a bench configuration at their ports."""

    def __init__(
        self,
        kind: str,
        world: StageWorld | RotaryWorld,
        ports: dict[str, SimPort],
        directory: Path,
        clock: Clock,
        toml_text: str,
        bench_name: str,
        own_directory: bool,
    ) -> None:
        self.kind = kind
        self.world = world
        self.ports = ports
        self.directory = directory
        self.clock = clock
        self.toml = toml_text
        self.bench_name = bench_name
        self._own_directory = own_directory
        self.config: BenchConfig = parse_bench_config(
            _toml_loads(toml_text), "simulated bench"
        ).bench(bench_name)

    def faults(self, role: str) -> Faults:
        if role not in self.ports:
            raise KeyError(
                f"the simulated {self.kind} bench has no role {role!r}; it has "
                f"{', '.join(self.ports)}"
            )
        return self.ports[role].faults

    def port_path(self, role: str) -> str:
        return self.ports[role].path

    def close(self) -> None:
        for port in {id(sim_port): sim_port for sim_port in self.ports.values()}.values():
            port.close()
        if self._own_directory:
            shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self) -> SimulatedBench:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _toml_loads(text: str) -> dict[str, object]:
    """A TOML document (its shape is for `parse_bench_config` to check)."""
    import tomllib

    return tomllib.loads(text)


def start_simulated_bench(
    scenario: str,
    kind: Literal["stage", "rotary"],
    clock: Clock,
    *,
    directory: str | Path | None = None,
    adc: bool = False,
    output_rate_hz: int | str = DEFAULT_OUTPUT_RATE_HZ,
    bus_addresses: tuple[int, ...] = (1, 2, 3),
    bench_name: str | None = None,
    transport: SimTransport = "pty",
    ambient: bool = False,
) -> SimulatedBench:
    """Start every instrument of a simulated bench; ports appear as symlinks in `directory`.

    transport "pty": each instrument behind a pseudo-terminal, as a USB adapter would be;
    "loopback": behind an in-memory line of this process (`simloop://` names, see `loopback`),
    the same drivers, transport and codecs without the pty, for callers that do not test the pty.

    stage: reference_sensor, measurement_sensor (family A), stage (family D, axes 1 and 2),
    and with `adc` the analog sensor behind the ADC (family C, physics of the seed003 preset).
    rotary: rotary_table (family D axis 3), triaxial_sensor (family A, 0x07) and an RS-485 bus
    with inclinometers at `bus_addresses`; the configuration names the first as turntable_sensor.
    With `ambient`, either kind also has an ambient_sensor: a thermo-hygrometer (family B, TH) on a
    port of its own (`ambient` firmware, the air's truth).
    """
    if kind not in ("stage", "rotary"):
        raise InputError(f"bench kind {kind!r} is not stage or rotary")
    own = directory is None
    folder = Path(tempfile.mkdtemp(prefix="tiltlab-sim-")) if directory is None else Path(directory)
    folder.mkdir(parents=True, exist_ok=True)
    name = bench_name or f"sim-{kind}"
    ports: dict[str, SimPort] = {}
    world: StageWorld | RotaryWorld
    try:
        if kind == "stage":
            world, ports, roles = _stage(
                scenario, clock, folder, adc, output_rate_hz, PORT_CLASSES[transport]
            )
            hardware = world.scenario.bench.model_dump()
        else:
            world, ports, roles = _rotary(
                scenario, clock, folder, output_rate_hz, bus_addresses, PORT_CLASSES[transport]
            )
            hardware = None
        if ambient:
            from service.instruments.sim.ambient import AmbientFirmware

            ports["ambient_sensor"] = PORT_CLASSES[transport](
                folder / "ambient_sensor", AmbientFirmware(clock)
            )
            roles["ambient_sensor"] = {
                "port": ports["ambient_sensor"].path,
                "baud": SIM_BAUD["rs485"],
                "address": "01",
            }
    except BaseException:
        for port in ports.values():
            port.close()
        if own:
            shutil.rmtree(folder, ignore_errors=True)
        raise
    config = _config_text(kind, scenario, clock, name, hardware, roles)
    return SimulatedBench(kind, world, ports, folder, clock, config, name, own)


def _config_text(
    kind: str,
    scenario: str,
    clock: Clock,
    name: str,
    hardware: Mapping[str, object] | None,
    roles: Roles,
) -> str:
    """The bench configuration (TOML) the daemon reads to find the simulated bench's ports."""
    lines = [
        f"# Simulated {kind} bench, scenario {scenario}, {clock.speed:g} times real time.",
        f"sim_speed = {clock.speed:g}",
        "",
        f"[benches.{name}]",
        f'kind = "{kind}"',
        f'description = "simulated {kind} bench, scenario {scenario}"',
        "",
    ]
    # the scenario's stages: the daemon converts degrees to pulses with its gearing
    if hardware is not None:
        lines.append(f"[benches.{name}.hardware]")
        lines.extend(f"{key} = {_toml_value(value)}" for key, value in hardware.items())
        lines.append("")
    for role, table in roles.items():
        lines.append(f"[benches.{name}.roles.{role}]")
        for key, value in table.items():
            lines.append(f"{key} = {_toml_value(value)}")
        lines.append("")
    return "\n".join(lines)


def _toml_value(v: object) -> str:
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


class SimRoleTable(TypedDict, total=False):
    """A simulated instrument's table in the bench configuration (`[benches.<name>.roles.<role>]`):
    its port, line speed, bus address or axis, and output rate, as the role's model reads them."""

    port: Required[str]
    baud: Required[int]
    address: int | str  # a binary inclinometer's number; an RS-485 address in hex ("01")
    axis: int  # the controller's axis
    output_rate_hz: int | str  # readings a second, or "continuous"


# Each role's table, by role
Roles = dict[str, SimRoleTable]


def _stage(
    scenario: str,
    clock: Clock,
    folder: Path,
    with_adc: bool,
    rate: int | str,
    port_class: type[SimPort],
) -> tuple[StageWorld, dict[str, SimPort], Roles]:
    sc = stage_scenario(scenario)
    adc_sc = load_scenario("seed003") if with_adc else None
    # the seed003 preset is a scale scenario
    assert adc_sc is None or isinstance(adc_sc, ScaleScenario)
    world = StageWorld(sc, clock, adc_scenario=adc_sc)
    ports: dict[str, SimPort] = {}
    roles: Roles = {}
    for role, prefix in (("reference_sensor", "ref"), ("measurement_sensor", "meas")):

        def read_xy(at_s: float | None = None, p: str = prefix) -> tuple[float, float]:
            return world.reading_deg(p, at_s)

        fw = BinaryFirmware(
            clock,
            read_xy,
            world.temp_c,
            address=0,
            baud=SIM_BAUD["binary"],
            output_mode=_mode(rate),
        )
        ports[role] = port_class(folder / role, fw)
        roles[role] = {
            "port": ports[role].path,
            "baud": SIM_BAUD["binary"],
            "address": 0,
            "output_rate_hz": rate,
        }
    ports["stage"] = port_class(folder / "stage", ControllerFirmware(world.axes))
    roles["stage"] = {"port": ports["stage"].path, "baud": SIM_BAUD["controller"]}
    if with_adc:
        ports["adc_sensor"] = port_class(folder / "adc_sensor", AdcFirmware(world.adc_counts))
        roles["adc_sensor"] = {"port": ports["adc_sensor"].path, "baud": SIM_BAUD["adc"]}
    return world, ports, roles


def _mode(rate: int | str) -> int:
    """The output mode the instrument keeps from its last configuration (as instruments store
    it)."""
    for code, hz in binary.OUTPUT_MODES.items():
        if hz == rate or (rate == "continuous" and hz is None):
            return code
    raise InputError(f"output rate {rate!r} is not one of the instrument's modes")


def _pair(sample: dict[str, float], prefix: str) -> tuple[float, float]:
    return sample[f"{prefix}_x_deg"], sample[f"{prefix}_y_deg"]


def _rotary(
    scenario: str,
    clock: Clock,
    folder: Path,
    rate: int | str,
    bus_addresses: tuple[int, ...],
    port_class: type[SimPort],
) -> tuple[RotaryWorld, dict[str, SimPort], Roles]:
    rot, tt = rotary_scenarios(scenario)
    world = RotaryWorld(rot, tt, clock, bus_addresses=bus_addresses)
    ports: dict[str, SimPort] = {}
    roles: Roles = {}
    ports["rotary_table"] = port_class(
        folder / "rotary_table", ControllerFirmware(world.axes, model="RT-360SIM")
    )
    roles["rotary_table"] = {
        "port": ports["rotary_table"].path,
        "baud": SIM_BAUD["controller"],
        "axis": 3,
    }
    tri = BinaryFirmware(
        clock,
        lambda _at_s: (0.0, 0.0),
        world.temp_c,
        address=0,
        baud=SIM_BAUD["binary"],
        read_sines=world.sines,
        output_mode=_mode(rate),
    )
    ports["triaxial_sensor"] = port_class(folder / "triaxial_sensor", tri)
    roles["triaxial_sensor"] = {
        "port": ports["triaxial_sensor"].path,
        "baud": SIM_BAUD["binary"],
        "address": 0,
        "output_rate_hz": rate,
    }

    def reader(a: int) -> Callable[[], tuple[float, float]]:
        return lambda: world.turntable_mrad(a)

    bus = Rs485BusFirmware({address: reader(address) for address in bus_addresses}, world.temp_c)
    ports["turntable_sensor"] = port_class(folder / "rs485_bus", bus)
    roles["turntable_sensor"] = {
        "port": ports["turntable_sensor"].path,
        "baud": SIM_BAUD["rs485"],
        "address": f"{bus_addresses[0]:02X}",
    }
    return world, ports, roles


__all__ = ["SimulatedBench", "start_simulated_bench"]
