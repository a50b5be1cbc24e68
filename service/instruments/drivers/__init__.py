"""Drivers per role: the lab's operations in the lab's units, over one family's bytes.

One module per instrument family: the binary inclinometers and the triaxial module (family A,
`inclinometer`), the RS-485 inclinometer (family B, `rs485_inclinometer`), the ADC of the analog
sensor (family C, `adc_sensor`), the ambient thermo-hygrometer (family B, `ambient_sensor`) and the
motion controller's axes and stage (family D, `controller_axis`); what they share (port, counters,
readings kept, polling) is `common`. Each driver class declares the protocol of
`service.instruments.base` it implements.
"""

from service.instruments.drivers.adc_sensor import AdcSensor
from service.instruments.drivers.ambient_sensor import Rs485Thermohygrometer
from service.instruments.drivers.common import RECENT_READINGS, SerialDriver
from service.instruments.drivers.controller_axis import (
    IDLE_POLL_MISSES,
    ControllerAxis,
    StageController,
)
from service.instruments.drivers.inclinometer import SYNC_ASKS, BinaryInclinometer, TriaxialModule
from service.instruments.drivers.rs485_inclinometer import Rs485Inclinometer

__all__ = [
    "IDLE_POLL_MISSES",
    "RECENT_READINGS",
    "SYNC_ASKS",
    "AdcSensor",
    "BinaryInclinometer",
    "ControllerAxis",
    "Rs485Inclinometer",
    "Rs485Thermohygrometer",
    "SerialDriver",
    "StageController",
    "TriaxialModule",
]
