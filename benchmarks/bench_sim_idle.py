"""Benchmark of what the daemon costs, idle, with its simulated stage bench.

    python benchmarks/bench_sim_idle.py [--speed 20] [--seconds 20]

Starts `tiltlab serve` on a free loopback port with a fresh data directory and the simulated
bench at --sim-speed N, waits for `serving on`, lets it settle (5 s), then reads the process's
CPU time (all threads: the simulated instruments' firmware, the drivers' readers, the
readings path, the web app) over --seconds of wall time: the share of one core. The same
figure does not depend on other load the way a time does, as long as the daemon gets the CPU
it asks for; the load average is printed beside it.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed", type=float, default=20.0)
    ap.add_argument("--seconds", type=float, default=20.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as data:
        env = {**os.environ, "TILTLAB_DATA_DIR": data}
        log = Path(data) / "serve.log"
        with log.open("w") as out:
            proc = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "service.cli",
                    "serve",
                    "--port",
                    str(free_port()),
                    "--sim-speed",
                    f"{args.speed:g}",
                ],
                env=env,
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        try:
            deadline = time.monotonic() + 120
            while "serving on" not in log.read_text():
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise SystemExit(f"the daemon did not start:\n{log.read_text()}")
                time.sleep(0.2)
            time.sleep(5.0)  # the bench connects and settles
            load_before = os.getloadavg()
            c0, t0 = cpu_seconds(proc.pid), time.monotonic()
            time.sleep(args.seconds)
            c1, t1 = cpu_seconds(proc.pid), time.monotonic()
            load_after = os.getloadavg()
        finally:
            proc.terminate()
            proc.wait(30)
    print(
        f"load average (1 min): before {load_before[0]:.2f}, after {load_after[0]:.2f}; "
        f"{os.cpu_count()} cores"
    )
    print(
        f"daemon idle at --sim-speed {args.speed:g}: {100 * (c1 - c0) / (t1 - t0):.1f} % of a core "
        f"over {t1 - t0:.1f} s"
    )


if __name__ == "__main__":
    main()
