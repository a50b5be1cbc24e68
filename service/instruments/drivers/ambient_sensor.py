"""Family (B) thermo-hygrometer: the bench's ambient sensor, polled for the air's temperature and
relative humidity (a job records them as the conditions of its calibration)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from service.clock import Clock
from service.instruments import rs485
from service.instruments.base import AmbientSensor, DeviceIdentity, Reading
from service.instruments.drivers.common import SerialDriver
from service.instruments.transport import DeviceError, SerialPort


class Rs485Thermohygrometer(SerialDriver, AmbientSensor):
    """ambient_sensor (family B, command TH): one address, on a port of its own or a bus it
    shares."""

    protocol = "rs485"

    def __init__(
        self,
        role: str,
        port: SerialPort,
        clock: Clock,
        timeout_s: float,
        address: int,
        poll_rate_hz: float | None,
        standard_uncertainty_c: float,
        standard_uncertainty_pct: float,
    ) -> None:
        super().__init__(role, port, clock, timeout_s)
        self.address = address
        self.poll_rate_hz = poll_rate_hz
        self.standard_uncertainty_c = standard_uncertainty_c
        self.standard_uncertainty_pct = standard_uncertainty_pct
        port.own(address)

    def _match(self, kind: type) -> Callable[[Any], bool]:
        def match(m: Any) -> bool:
            return isinstance(m, kind) and getattr(m, "address", None) == self.address

        return match

    async def start(self) -> None:
        await super().start()
        if self.poll_rate_hz:
            self._start_polling(self.poll_rate_hz, self.read_ambient)

    async def read_ambient(self) -> Reading:
        """The air's temperature and relative humidity now; an out-of-range answer is refused, not
        kept."""
        req = rs485.encode_request(rs485.Rs485Request(self.address, "TH"))
        ans: rs485.Rs485Ambient = await self._ask(
            req, self._match(rs485.Rs485Ambient), "read ambient conditions"
        )
        if ans.status != 0:
            raise DeviceError(
                f"{self.role}: the thermo-hygrometer reports its reading out of range "
                f"(ST={ans.status})"
            )
        reading = self._stamp(temp_c=ans.temp_c, humidity_pct=ans.humidity_pct, status=ans.status)
        self._latest = reading
        return reading

    async def identify(self) -> DeviceIdentity:
        req = rs485.encode_request(rs485.Rs485Request(self.address, "ID"))
        ans: rs485.Rs485Identity = await self._ask(
            req, self._match(rs485.Rs485Identity), "identify"
        )
        self.identity = DeviceIdentity(model=ans.model, serial=ans.serial, firmware=ans.firmware)
        return self.identity
