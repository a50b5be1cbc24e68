"""pyserial's handler for `simloop://` names: a serial port whose other end is a simulated
instrument in this process (see `loopback`). Found by `serial.serial_for_url`, never imported by
name."""

from __future__ import annotations

from typing import Any

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from service.instruments.sim.loopback import MemoryLine, line_named


class Serial(SerialBase):  # type: ignore[misc]  # pyserial ships no type information
    """The driver's end of a memory line; settings (baud, parity) are accepted and change
    nothing."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._line: MemoryLine | None = None
        self._generation = 0
        super().__init__(*args, **kwargs)

    def open(self) -> None:
        if self._line is not None:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        line = line_named(str(self._port))
        self._generation = line.open_host()
        self._line = line
        self.is_open = True
        self.reset_input_buffer()  # as pyserial's port on a device does when it opens

    def close(self) -> None:
        line, self._line = self._line, None
        if line is not None:
            line.close_host(self._generation)
        self.is_open = False

    def _reconfigure_port(self) -> None:
        """A memory line has no baud rate or parity to set."""

    def _open_line(self) -> MemoryLine:
        if not self.is_open or self._line is None:
            raise PortNotOpenError()
        return self._line

    @property
    def in_waiting(self) -> int:
        return self._open_line().waiting(self._generation)

    def read(self, size: int = 1) -> bytes:
        return self._open_line().read_host(self._generation, size, self._timeout)

    def write(self, data: bytes) -> int:
        payload = bytes(data)
        self._open_line().write_host(self._generation, payload)
        return len(payload)

    def reset_input_buffer(self) -> None:
        self._open_line().discard_for_host(self._generation)

    def reset_output_buffer(self) -> None:
        """Writes leave at once."""

    def flush(self) -> None:
        """Writes leave at once."""
