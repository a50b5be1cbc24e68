"""Family (B) driver: an RS-485 inclinometer (the turntable sensor), one address on a bus that
other instruments may share; milliradians on the wire, polled."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from service.clock import Clock
from service.instruments import rs485
from service.instruments.base import DeviceIdentity, Reading, TiltSensor
from service.instruments.drivers.common import SerialDriver, present
from service.instruments.transport import SerialPort


class Rs485Inclinometer(SerialDriver, TiltSensor):
    """turntable_sensor (family B): one address on a bus that other instruments may share."""

    protocol = "rs485"
    resolution_deg = 1e-6 * 180.0 / math.pi  # milliradians with three decimals: 1 µrad

    def __init__(
        self,
        role: str,
        port: SerialPort,
        clock: Clock,
        timeout_s: float,
        address: int,
        poll_rate_hz: float | None = None,
    ) -> None:
        super().__init__(role, port, clock, timeout_s)
        self.address = address
        self.poll_rate_hz = poll_rate_hz
        port.own(address)

    def _match(self, kind: type, **fields: object) -> Callable[[Any], bool]:
        def match(m: Any) -> bool:
            return (
                isinstance(m, kind)
                and getattr(m, "address", None) == self.address
                and all(getattr(m, field) == wanted for field, wanted in fields.items())
            )

        return match

    async def start(self) -> None:
        await super().start()
        if self.poll_rate_hz:
            self._start_polling(self.poll_rate_hz, self.read_tilt)

    async def read_tilt(self) -> Reading:
        req = rs485.encode_request(rs485.Rs485Request(self.address, "RD"))
        ans: rs485.Rs485Reading = await self._ask(req, self._match(rs485.Rs485Reading), "read tilt")
        reading = self._stamp(
            x_deg=rs485.mrad_to_deg(ans.x_mrad),
            y_deg=rs485.mrad_to_deg(ans.y_mrad),
            temp_c=ans.temp_c,
            status=ans.status,
        )
        self._latest = reading
        return reading

    async def read_temperature(self) -> float:
        return float(present((await self.read_tilt()).temp_c, "read temperature"))

    async def _zero(self, relative: bool) -> None:
        req = rs485.encode_request(rs485.Rs485Request(self.address, "ZR" if relative else "ZA"))
        await self._ask(
            req,
            self._match(rs485.Rs485ZeroDone, relative=relative),
            "set relative zero" if relative else "set absolute zero",
        )

    async def set_relative_zero(self) -> None:
        await self._zero(True)

    async def set_absolute_zero(self) -> None:
        await self._zero(False)

    async def identify(self) -> DeviceIdentity:
        req = rs485.encode_request(rs485.Rs485Request(self.address, "ID"))
        ans: rs485.Rs485Identity = await self._ask(
            req, self._match(rs485.Rs485Identity), "identify"
        )
        self.identity = DeviceIdentity(model=ans.model, serial=ans.serial, firmware=ans.firmware)
        return self.identity
