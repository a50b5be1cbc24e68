"""`tiltlab devices`: ask every role of a bench configuration who is there, and say what answered.

Each role is probed with its own family's request at its own address, without changing the
instrument's settings. A role that does not answer as expected gets one line naming the
role, the port and what was expected; then the exit status is 2.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from service.commands._args import add_command

if TYPE_CHECKING:  # the bench and its drivers are imported when the command runs, not by --help
    from service.clock import Clock
    from service.instruments.bench_config import BenchConfig, PortRole
    from service.instruments.wiring import RoleDriver

EXPECTED = {
    "reference_sensor": "a 0x68 binary inclinometer",
    "measurement_sensor": "a 0x68 binary inclinometer",
    "triaxial_sensor": "a 0x68 triaxial module (command 0x07)",
    "turntable_sensor": "an RS-485 inclinometer",
    "adc_sensor": "an ADC answering ID?",
    "stage": "a stage controller answering on axes 1 and 2",
    "rotary_table": "a controller answering on the rotary axis",
    "ambient_sensor": "an RS-485 thermo-hygrometer (command TH)",
}


def expected(role: str, spec: PortRole) -> str:
    from service.instruments.bench_config import (
        AmbientSensorRole,
        BinaryInclinometerRole,
        RotaryTableRole,
        Rs485InclinometerRole,
    )

    what = EXPECTED[role]
    if isinstance(spec, BinaryInclinometerRole):
        what += f" at address 0x{spec.address:02X}"
    elif isinstance(spec, Rs485InclinometerRole | AmbientSensorRole):
        what += f" at address {spec.address.upper()}"
    elif isinstance(spec, RotaryTableRole):
        what = f"a controller answering on axis {spec.axis}"
    return what


async def _probe(role: str, driver: RoleDriver) -> str:
    """What answered, in words; raises DeviceError with the reason otherwise.

    Each role has its family's driver (service.instruments.wiring.make_driver): the stage its
    controller, the rotary table one axis, the triaxial module, the binary inclinometers, the
    RS-485 inclinometer, the ADC.
    """
    from service.instruments.drivers import (
        BinaryInclinometer,
        ControllerAxis,
        Rs485Inclinometer,
        Rs485Thermohygrometer,
        StageController,
        TriaxialModule,
    )

    if isinstance(driver, StageController):
        ident = await driver.x.identify()
        await driver.y.position_pulses()
        return (
            f"{ident.model} serial {ident.serial}, axes 1 and 2 at "
            f"{await driver.x.position_deg():.4f}, {await driver.y.position_deg():.4f} deg"
        )
    if isinstance(driver, ControllerAxis):
        ident = await driver.identify()
        return (
            f"{ident.model} serial {ident.serial}, axis {driver.axis} at "
            f"{await driver.position_deg():.3f} deg"
        )
    if isinstance(driver, TriaxialModule):
        reading = await driver.read_sines()
        return (
            f"triaxial module at address 0x{driver.address:02X}: sines {reading.sx:+.6f} "
            f"{reading.sy:+.6f} {reading.sz:+.6f} g"
        )
    if isinstance(driver, BinaryInclinometer):
        reading = await driver.read_tilt()
        return (
            f"binary inclinometer at address 0x{driver.address:02X}: x {reading.x_deg:+.4f} y "
            f"{reading.y_deg:+.4f} deg"
        )
    ident = await driver.identify()
    if isinstance(driver, Rs485Inclinometer):
        reading = await driver.read_tilt()
        return (
            f"{ident.model} serial {ident.serial} firmware {ident.firmware} at address "
            f"{driver.address:02X}: x {reading.x_deg:+.5f} y {reading.y_deg:+.5f} deg"
        )
    if isinstance(driver, Rs485Thermohygrometer):
        reading = await driver.read_ambient()
        return (
            f"{ident.model} serial {ident.serial} at address {driver.address:02X}: air "
            f"{reading.temp_c:+.2f} °C, relative humidity {reading.humidity_pct:.1f} %"
        )
    reading = await driver.read_counts(1)
    return f"{ident.model} serial {ident.serial}: {reading.counts:.0f} counts"


def _answered_elsewhere(role: str, spec: PortRole, senders: list[int]) -> str | None:
    """Who answered instead, when the port heard another address (or axis) than the role's."""
    from service.instruments.bench_config import (
        AmbientSensorRole,
        BinaryInclinometerRole,
        Rs485InclinometerRole,
    )

    if senders and isinstance(
        spec, BinaryInclinometerRole | Rs485InclinometerRole | AmbientSensorRole
    ):
        return "answered from address " + ", ".join(
            f"0x{address:02X}" if isinstance(spec, BinaryInclinometerRole) else f"{address:02X}"
            for address in senders
        )
    if senders and role in ("stage", "rotary_table"):
        return "answered on axis " + ", ".join(map(str, senders))
    return None


def _why(role: str, spec: PortRole, driver: RoleDriver) -> str:
    from service.instruments.drivers import StageController

    port = driver.x.port if isinstance(driver, StageController) else driver.port
    if port.state != "connected":
        return f"cannot be opened ({port.error or 'not found'})"
    elsewhere = _answered_elsewhere(role, spec, sorted(port.foreign_senders))
    if elsewhere is not None:
        return elsewhere
    st = port.decoder.stats
    if st.resyncs or st.bad_checksum or port.decoder.pending:
        return f"sent {port.bytes_read} bytes in another protocol"
    return f"no answer within {spec.timeout_s:g} s"


async def probe_bench(config: BenchConfig, clock: Clock) -> list[tuple[str, str, bool, str]]:
    """(role, port, answered, what answered or why not) for every role."""
    import asyncio

    from service.instruments.drivers import StageController
    from service.instruments.transport import DeviceError, PortRegistry
    from service.instruments.wiring import make_driver

    registry = PortRegistry()
    results = []
    drivers = {
        role: make_driver(role, spec, config, clock, registry)
        for role, spec in config.role_specs.items()
    }
    ports = {
        id(port): port
        for driver in drivers.values()
        for port in ([driver.x.port] if isinstance(driver, StageController) else [driver.port])
    }
    for port in ports.values():
        port.start()
    try:
        await asyncio.gather(
            *(asyncio.to_thread(port.wait_connected, 2.0) for port in ports.values())
        )
        for role, driver in drivers.items():
            spec = config.role(role)
            try:
                results.append((role, spec.where, True, await _probe(role, driver)))
            except DeviceError:
                results.append(
                    (
                        role,
                        spec.where,
                        False,
                        (f"{_why(role, spec, driver)}; expected {expected(role, spec)}"),
                    )
                )
    finally:
        for port in ports.values():
            port.stop()
    return results


def run(args: argparse.Namespace) -> int:
    import asyncio

    from service.clock import Clock
    from service.instruments.bench_config import load_bench_config

    benches = load_bench_config(args.config)
    config = benches.bench(args.bench)
    results = asyncio.run(probe_bench(config, Clock(benches.sim_speed or 1.0)))
    width = max(len(result[0]) for result in results)
    bad = 0
    for role, where, ok, text in results:
        if ok:
            print(f"{role:<{width}}  {where}  {text}")
        else:
            bad += 1
            print(f"tiltlab devices: error: role {role} on port {where}: {text}", file=sys.stderr)
    return 2 if bad else 0  # a role that does not answer as configured is bad configuration


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = add_command(
        sub,
        "devices",
        "probe every role of a bench configuration and say what answered",
        examples=["tiltlab devices --config bench.toml"],
    )
    parser.add_argument(
        "--config", required=True, metavar="FILE", help="bench configuration file (TOML)"
    )
    parser.add_argument(
        "--bench",
        default=None,
        metavar="NAME",
        help="bench name, when the file describes several (default: the only one)",
    )
    parser.set_defaults(handler=run)
