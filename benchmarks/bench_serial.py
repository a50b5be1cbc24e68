"""Benchmark of the serial path: a family (A) inclinometer's continuous output through a pty.

    python benchmarks/bench_serial.py [--seconds 60]

A simulated inclinometer in a child process sends 0x84 frames back to back, paced at the
line rate of 115200 baud (13-byte frames: 886 frames per second), on a pseudo-terminal.
The daemon's own reading side (SerialPort: pyserial reader thread and the incremental
codec) reads them. The frames carry a running count (x = +k·0.0001°, y = −x), so every
frame received can be checked: lost frames are gaps, corrupted ones break the pattern.

Prints: frames sent and delivered (fraction), frames corrupted, checksum failures and
resyncs, the reader thread's CPU time per 1,000 frames, and the codec's raw throughput
in-process (frames per second, fed in 4 KiB chunks). Figures are in docs/instruments.md.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import platform
import tempfile
import time
from pathlib import Path

from service.clock import Clock
from service.instruments import binary
from service.instruments.framing import Decoder
from service.instruments.transport import SerialPort

BAUD = 115200
MODULO = 10_000_000  # the count wraps within the 7 digits of the BCD angle


def _count_xy(counter: list[int]):
    def read() -> tuple[float, float]:
        k = counter[0] % MODULO
        counter[0] += 1
        return k / 10_000, -k / 10_000

    return read


def simulator(link: str, conn) -> None:
    """Child process: one inclinometer on a pty at `link`, until told to stop; reports what it
    sent."""
    from service.instruments.sim.firmware import BinaryFirmware
    from service.instruments.sim.pty import SimPort

    counter = [0]
    fw = BinaryFirmware(Clock(1.0), _count_xy(counter), lambda: 21.0, baud=BAUD)
    port = SimPort(Path(link), fw)
    conn.send("ready")
    conn.recv()
    port.close()
    conn.send(
        {
            "auto_frames": fw.auto_frames,
            "sent_frames": port.sent_frames,
            "overflow_bytes": port.overflow_bytes,
        }
    )


class Checker:
    """Counts frames and checks each carries the running count (gaps are losses, breaks
    corruption)."""

    def __init__(self) -> None:
        self.frames = 0
        self.corrupted = 0
        self.gaps = 0
        self.last: int | None = None

    def __call__(self, msg, _utc) -> None:
        if not isinstance(msg, binary.BinaryAnswer) or msg.command != 0x84:
            return
        self.frames += 1
        k = round(msg.x_deg * 10_000)
        if msg.y_deg != -msg.x_deg and not (k == 0 and msg.y_deg == 0):
            self.corrupted += 1
            return
        if self.last is not None and k != (self.last + 1) % MODULO:
            self.gaps += 1
        self.last = k


async def measure(link: str, seconds: float) -> dict:
    port = SerialPort(link, binary.parse_answers, baud=BAUD)
    check = Checker()
    port.add_listener(check)
    port.start()
    assert await asyncio.to_thread(port.wait_connected, 10), "the pty did not open"
    set_mode = lambda code: binary.encode(binary.BinaryRequest(0, binary.SET_OUTPUT, code))  # noqa: E731
    match = lambda m: m.command == binary.SET_OUTPUT | binary.ANSWER  # noqa: E731
    await port.request(set_mode(0x07), match, 2.0, "continuous output on")
    cpu_clock = time.pthread_getcpuclockid(port._thread.ident)
    cpu0, f0, t0 = time.clock_gettime(cpu_clock), check.frames, time.monotonic()
    await asyncio.sleep(seconds)
    cpu1, f1, t1 = time.clock_gettime(cpu_clock), check.frames, time.monotonic()
    await port.request(set_mode(0x00), match, 2.0, "continuous output off")
    await asyncio.sleep(0.5)  # the last frames drain
    port.stop()
    st = port.decoder.stats
    return {
        "received": check.frames,
        "corrupted": check.corrupted,
        "gaps": check.gaps,
        "bad_checksum": st.bad_checksum,
        "resyncs": st.resyncs,
        "window_frames": f1 - f0,
        "window_s": t1 - t0,
        "cpu_s": cpu1 - cpu0,
    }


def parser_throughput(n: int = 200_000) -> float:
    frames = b"".join(
        binary.encode(binary.BinaryAnswer(0, 0x84, x_deg=(k % 9999) / 10_000, y_deg=-0.5))
        for k in range(n)
    )
    dec = Decoder(binary.parse_answers)
    t0 = time.perf_counter()
    got = 0
    for i in range(0, len(frames), 4096):
        got += len(dec.feed(frames[i : i + 4096]))
    dt = time.perf_counter() - t0
    assert got == n
    return n / dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="tiltlab-bench-") as folder:
        link = str(Path(folder) / "inclinometer")
        parent, child = mp.Pipe()
        proc = mp.get_context("spawn").Process(target=simulator, args=(link, child), daemon=True)
        proc.start()
        assert parent.recv() == "ready"
        result = asyncio.run(measure(link, args.seconds))
        parent.send("stop")
        sent = parent.recv()
        proc.join(10)
    line_rate = BAUD / 10 / 13
    delivered = result["received"] / sent["auto_frames"]
    print(f"python {platform.python_version()} on {platform.machine()}, {mp.cpu_count()} cpus")
    print(
        f"continuous output for {result['window_s']:.1f} s at {BAUD} baud (line rate "
        f"{line_rate:.0f} frames/s)"
    )
    print(
        f"  frames sent {sent['auto_frames']}, delivered {result['received']} "
        f"({100 * delivered:.2f} %), "
        f"{result['window_frames'] / result['window_s']:.0f} frames/s in the window"
    )
    print(
        f"  corrupted {result['corrupted']}, gaps in the count {result['gaps']}, "
        f"checksum failures {result['bad_checksum']}, resyncs {result['resyncs']}, "
        f"bytes the pty could not take {sent['overflow_bytes']}"
    )
    print(
        f"  reader thread CPU {1e6 * result['cpu_s'] / max(result['window_frames'], 1):.1f} ms "
        f"per 1,000 frames ({100 * result['cpu_s'] / result['window_s']:.1f} % of one core)"
    )
    print(f"codec raw throughput: {parser_throughput():,.0f} frames/s (in-process, 4 KiB chunks)")


if __name__ == "__main__":
    main()
