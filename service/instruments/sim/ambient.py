"""A simulated thermo-hygrometer (family B, command TH): the laboratory's air as a bench's ambient
sensor reads it.

The air is the simulated truth: a temperature and a relative humidity that drift slowly
(sinusoidally over bench time) around the values given; each answer adds the instrument's own
reading noise and is rounded to the digits the protocol carries. `truth_c`/`truth_pct` give what a
perfect instrument would read.
"""

from __future__ import annotations

import math

import numpy as np

from service.clock import Clock
from service.instruments import rs485
from service.instruments.framing import Decoder
from service.instruments.sim.firmware import AnsweringFirmware


class AmbientFirmware(AnsweringFirmware):
    family = "rs485"

    def __init__(
        self,
        clock: Clock,
        *,
        address: int = 1,
        temp_c: float = 20.3,
        humidity_pct: float = 45.0,
        drift_c: float = 0.15,
        drift_pct: float = 1.5,
        period_s: float = 1800.0,
        noise_c: float = 0.02,
        noise_pct: float = 0.3,
        seed: int = 7,
        model: str = "TH-200SIM",
        serial: str = "SIM-TH01",
    ) -> None:
        self.clock = clock
        self.address = address
        self.temp_c, self.humidity_pct = temp_c, humidity_pct
        self.drift_c, self.drift_pct, self.period_s = drift_c, drift_pct, period_s
        self.noise_c, self.noise_pct = noise_c, noise_pct
        self.model, self.serial = model, serial
        self.rng = np.random.default_rng(seed)
        self.decoder = Decoder(rs485.parse_requests)

    def truth_c(self, bench_s: float | None = None) -> float:
        t = self.clock.monotonic() if bench_s is None else bench_s
        return self.temp_c + self.drift_c * math.sin(2 * math.pi * t / self.period_s)

    def truth_pct(self, bench_s: float | None = None) -> float:
        t = self.clock.monotonic() if bench_s is None else bench_s
        return self.humidity_pct + self.drift_pct * math.sin(2 * math.pi * t / self.period_s + 1.0)

    def handle(self, data: bytes) -> list[bytes]:
        out = []
        for req in self.decoder.feed(data):
            if req.address != self.address:
                continue
            if req.command == "TH":
                t = round(self.truth_c() + float(self.rng.normal(0.0, self.noise_c)), 2)
                rh = round(
                    min(
                        max(self.truth_pct() + float(self.rng.normal(0.0, self.noise_pct)), 0.0),
                        100.0,
                    ),
                    1,
                )
                msg: rs485.Rs485Answer = rs485.Rs485Ambient(self.address, t, rh, 0)
            elif req.command == "ID":
                msg = rs485.Rs485Identity(self.address, self.model, self.serial, "1.2")
            else:
                continue  # a thermo-hygrometer has no tilt to read or zero: it answers nothing
            out.append(rs485.encode(msg))
        return out

    def corrupt_checksum(self, frame: bytes) -> bytes:
        cs = int(frame[-4:-2], 16) ^ 0x21
        return frame[:-4] + f"{cs:02X}".encode() + frame[-2:]
