"""`tiltlab sim`: a whole simulated bench on pseudo-terminals, until interrupted.

Prints each role's port and the bench configuration that names them (also written to a
file), so `tiltlab serve` and `tiltlab devices` can use the simulated instruments exactly
as they would use real ones.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path

from service.commands._args import add_command, seconds, speed
from service.errors import InputError

FAMILY_WORDS = {
    "binary": "0x68 binary frames",
    "rs485": "RS-485 ASCII",
    "adc": "ADC ASCII",
    "controller": "controller ASCII",
}


def run(args: argparse.Namespace) -> int:
    from service.clock import Clock
    from service.instruments.bench_config import PROTOCOL_OF_ROLE
    from service.instruments.sim import fastest_speed, start_simulated_bench
    from service.io.datasets import check_output_path, write_text_atomic

    if not 0 < args.speed <= 10_000:
        raise InputError(f"--speed {args.speed:g}: give a factor above 0 and at most 10000")
    limit, why = fastest_speed(args.bench)
    if args.speed > limit:
        raise InputError(
            f"--speed {args.speed:g} is more than the simulated {args.bench} bench can run: "
            f"{why}, so at most {limit:g} times real time"
        )
    if args.out is not None:
        check_output_path(args.out)
    if args.duration is not None and args.duration <= 0:
        raise InputError(f"--duration {args.duration:g}: give seconds above 0")
    bench = start_simulated_bench(
        args.scenario, args.bench, Clock(args.speed), directory=args.dir, adc=args.adc
    )
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        out = Path(args.out) if args.out is not None else bench.directory / "bench.toml"
        write_text_atomic(out, bench.toml)
        for role, port in bench.ports.items():
            spec = bench.config.role(role)
            print(
                f"{role:<20} {port.path}  ({FAMILY_WORDS[PROTOCOL_OF_ROLE[role]]}, {spec.baud} "
                "baud)"
            )
        print(f"bench configuration: {out}")
        print(bench.toml, flush=True)
        print(
            f"tiltlab sim: {args.bench} bench of scenario {args.scenario} running at "
            f"{args.speed:g} x real time; Ctrl-C stops it",
            file=sys.stderr,
            flush=True,
        )
        try:
            stop.wait(args.duration)
        except KeyboardInterrupt:
            pass
    finally:
        signal.signal(signal.SIGTERM, previous)
        bench.close()
    return 0


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = add_command(
        sub,
        "sim",
        "run simulated instruments on pseudo-terminals and print their bench configuration",
        description="Start simulated instruments that speak the real instruments' bytes on "
        "pseudo-terminals,\nwrite the bench configuration naming their ports, and run "
        "until Ctrl-C (or --duration).",
        examples=[
            "tiltlab sim --dir /tmp/bench",
            "tiltlab serve --bench-config /tmp/bench/bench.toml",
        ],
    )
    parser.add_argument(
        "--scenario",
        default="seed000",
        metavar="NAME_OR_FILE",
        help="scenario preset or file that drives the physics",
    )
    parser.add_argument("--bench", choices=["stage", "rotary"], default="stage", help="which bench")
    parser.add_argument(
        "--speed",
        type=speed,
        default=1.0,
        help="bench seconds per real second (moves, output rates)",
    )
    parser.add_argument(
        "--adc", action="store_true", help="stage bench: add the analog sensor behind the ADC"
    )
    parser.add_argument(
        "--dir",
        default=None,
        metavar="FOLDER",
        help="folder for the port links (default: a new temporary folder)",
    )
    parser.add_argument(
        "--out",
        default=None,
        metavar="FILE",
        help="bench configuration file to write (default: bench.toml in --dir)",
    )
    parser.add_argument(
        "--duration",
        type=seconds,
        default=None,
        metavar="SECONDS",
        help="stop after this many seconds (default: until Ctrl-C)",
    )
    parser.set_defaults(handler=run)
