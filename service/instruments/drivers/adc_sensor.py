"""Family (C) driver: the 12-bit ADC in front of the analog tilt sensor, counts on the wire,
polled."""

from __future__ import annotations

from service.clock import Clock
from service.instruments import adc
from service.instruments.base import AnalogSensor, DeviceIdentity, Reading
from service.instruments.drivers.common import SerialDriver
from service.instruments.transport import SerialPort


class AdcSensor(SerialDriver, AnalogSensor):
    """adc_sensor (family C): counts of the 12-bit ADC, a mean of n conversions per reading."""

    protocol = "adc"

    def __init__(
        self,
        role: str,
        port: SerialPort,
        clock: Clock,
        timeout_s: float,
        conversions: int = 1,
        poll_rate_hz: float | None = None,
    ) -> None:
        super().__init__(role, port, clock, timeout_s)
        self.conversions = conversions
        self.poll_rate_hz = poll_rate_hz

    async def start(self) -> None:
        await super().start()
        if self.poll_rate_hz:
            self._start_polling(self.poll_rate_hz, lambda: self.read_counts(self.conversions))

    async def read_counts(self, conversions: int = 1) -> Reading:
        n = None if conversions == 1 else conversions
        req = adc.encode_request(adc.AdcRequest(n))
        ans: adc.AdcCounts = await self._ask(
            req, lambda m: isinstance(m, adc.AdcCounts) and m.conversions == n, "read counts"
        )
        reading = self._stamp(counts=ans.counts)
        self._latest = reading
        return reading

    async def identify(self) -> DeviceIdentity:
        ans: adc.AdcIdentity = await self._ask(
            adc.encode_request(adc.AdcRequest(identify=True)),
            lambda m: isinstance(m, adc.AdcIdentity),
            "identify",
        )
        self.identity = DeviceIdentity(model=ans.model, serial=ans.serial)
        return self.identity
