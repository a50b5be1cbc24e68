"""Family (D) drivers: one axis of the motion controller (the rotary table, a swing stage) and the
`stage` role's two axes on one port; pulses on the wire, degrees for callers."""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import replace

from service.clock import Clock
from service.instruments import controller
from service.instruments.base import (
    AxisState,
    DeviceIdentity,
    DeviceStatus,
    MotionAxis,
    TwoAxisStage,
)
from service.instruments.controller import Mnemonic
from service.instruments.drivers.common import SerialDriver, present
from service.instruments.transport import DeviceError, DeviceRefused, DeviceTimeout, SerialPort

IDLE_POLL_MISSES = 3  # unanswered state queries in a row before waiting for a move gives up
ERROR_QUERY_PATIENCE = 3  # the error code's answer is waited for this many port timeouts


class ControllerAxis(SerialDriver, MotionAxis):
    """One axis of a family (D) controller, in pulses on the wire and degrees for callers."""

    protocol = "controller"

    def __init__(
        self,
        role: str,
        port: SerialPort,
        clock: Clock,
        timeout_s: float,
        axis: int,
        pulse_deg: float,
        velocity_pulses_per_s: int | None = None,
        soft_limits_deg: tuple[float, float] | None = None,
    ) -> None:
        super().__init__(role, port, clock, timeout_s)
        self.axis = axis
        self.pulse_deg = pulse_deg
        port.own(axis)
        self.velocity_pulses_per_s = velocity_pulses_per_s
        self.soft_limits_deg = soft_limits_deg

    async def start(self) -> None:
        await super().start()
        if self.port.wait_connected(0):
            with contextlib.suppress(DeviceError):
                await self.configure()

    async def configure(self) -> None:
        """Velocity and soft limits from the bench configuration."""
        if self.velocity_pulses_per_s is not None:
            await self._send(Mnemonic.VELOCITY, self.velocity_pulses_per_s)
        if self.soft_limits_deg is not None:
            lo, hi = (round(limit_deg / self.pulse_deg) for limit_deg in self.soft_limits_deg)
            await self._send(Mnemonic.SOFT_LIMIT_LOW, lo)
            await self._send(Mnemonic.SOFT_LIMIT_HIGH, hi)

    async def _send(self, command: Mnemonic, value: int | None = None) -> None:
        await self.port.send(
            controller.encode_command(controller.ControllerCommand(self.axis, command, value))
        )

    async def _query(self, command: Mnemonic) -> controller.ControllerAnswer:
        """Ask a value. The error code is waited for longer than other answers: asking it clears it,
        so it cannot be asked again when a loaded host holds its answer past one timeout."""
        req = controller.encode_command(
            controller.ControllerCommand(self.axis, command, query=True)
        )
        patience = ERROR_QUERY_PATIENCE if command == Mnemonic.LAST_ERROR else 1
        answer: controller.ControllerAnswer = await self._ask(
            req,
            lambda m: (
                isinstance(m, controller.ControllerAnswer)
                and m.axis == self.axis
                and m.command == command
            ),
            f"axis {self.axis} {command}?",
            timeout_s=self.timeout_s * patience,
        )
        return answer

    async def _checked(self, command: Mnemonic, value: int | None, what: str) -> None:
        """Send a command the controller does not answer, then ask its error code: refusals
        raise."""
        await self._send(command, value)
        code = (await self._query(Mnemonic.LAST_ERROR)).value
        if code:
            raise DeviceRefused(
                f"{self.role}: axis {self.axis} {what}: "
                f"{controller.ERROR_NAMES.get(code, f'error {code}')}"
            )

    async def identify(self) -> DeviceIdentity:
        ans = await self._query(Mnemonic.IDENTITY)
        model, _, serial = str(present(ans.text, "identify")).partition(" ")
        self.identity = DeviceIdentity(model=model, serial=serial)
        return self.identity

    async def move_to_pulses(self, pulses: int) -> None:
        await self._checked(Mnemonic.MOVE_TO, int(pulses), f"move to {int(pulses)} pulses")

    async def move_by_pulses(self, pulses: int) -> None:
        await self._checked(Mnemonic.MOVE_BY, int(pulses), f"move by {int(pulses)} pulses")

    async def move_to_deg(self, angle_deg: float) -> int:
        pulses = round(angle_deg / self.pulse_deg)
        await self.move_to_pulses(pulses)
        return pulses

    async def position_pulses(self) -> int:
        return int(present((await self._query(Mnemonic.POSITION)).value, "query TP"))

    async def position_deg(self) -> float:
        return await self.position_pulses() * self.pulse_deg

    async def velocity_pulses(self) -> int:
        return int(present((await self._query(Mnemonic.VELOCITY)).value, "query VA"))

    async def soft_limits_pulses(self) -> tuple[int, int]:
        return (
            int(present((await self._query(Mnemonic.SOFT_LIMIT_LOW)).value, "query SL")),
            int(present((await self._query(Mnemonic.SOFT_LIMIT_HIGH)).value, "query SR")),
        )

    async def last_error(self) -> int:
        return int(present((await self._query(Mnemonic.LAST_ERROR)).value, "query TE"))

    async def state(self) -> AxisState:
        code = int(present((await self._query(Mnemonic.STATE)).value, "query TS"))
        return controller.STATE_NAMES.get(code, "error")  # type: ignore[return-value]

    async def wait_until_idle(self, timeout_s: float, poll_s: float = 0.05) -> float:
        """Poll the state until ready. A state query left unanswered (an answer lost on the line) is
        polled again; IDLE_POLL_MISSES of them in a row raise.

        The axis stopped between the last query that found it moving and the first that found it
        ready: the midpoint of the two queries' bench times is returned, not the later one, which
        would count half a poll cycle (the sleep, and the answer's round trip, which a sped-up or
        loaded simulation stretches) as moving every time."""
        deadline = self.clock.monotonic() + timeout_s
        misses = 0
        moving_asked: float | None = None
        while True:
            asked = self.clock.monotonic()
            try:
                state = await self.state()
            except DeviceTimeout:
                misses += 1
                if misses >= IDLE_POLL_MISSES or self.clock.monotonic() > deadline:
                    raise
                continue
            misses = 0
            if state == "ready":
                return asked if moving_asked is None else 0.5 * (moving_asked + asked)
            moving_asked = asked
            if state in ("hard_limit", "error"):
                code = await self.last_error()
                raise DeviceError(
                    f"{self.role}: axis {self.axis} stopped in state {state}"
                    f" ({controller.ERROR_NAMES.get(code, code)})"
                )
            if self.clock.monotonic() > deadline:
                raise DeviceTimeout(
                    f"{self.role}: axis {self.axis} still {state} after {timeout_s:g} s"
                )
            await self.clock.sleep(poll_s)

    async def stop(self) -> None:
        await self._send(Mnemonic.STOP)

    async def home(self) -> None:
        await self._checked(Mnemonic.HOME, None, "home")


class StageController(TwoAxisStage):
    """The `stage` role: two axes of one controller, 1 upper (x) and 2 lower (y), on one port."""

    protocol = "controller"

    def __init__(self, role: str, x: ControllerAxis, y: ControllerAxis) -> None:
        self.role = role
        self._x = x
        self._y = y
        self.axes = {"x": x, "y": y}

    @property
    def x(self) -> ControllerAxis:
        """Axis 1, the upper stage."""
        return self._x

    @property
    def y(self) -> ControllerAxis:
        """Axis 2, the lower stage."""
        return self._y

    @property
    def status(self) -> DeviceStatus:
        x_status = self.x.status
        x_status.counters.timeouts += self.y.timeouts
        return replace(x_status, role=self.role)

    async def start(self) -> None:
        await self.x.start()
        await self.y.start()

    async def close(self) -> None:
        await self.y.close()
        await self.x.close()

    async def identify(self) -> DeviceIdentity:
        ident = await self.x.identify()
        self.y.identity = ident
        return ident

    async def move_to_deg(self, x_deg: float, y_deg: float) -> tuple[int, int]:
        """Start both axes; returns the pulses commanded."""
        return await self.x.move_to_deg(x_deg), await self.y.move_to_deg(y_deg)

    async def position_deg(self) -> tuple[float, float]:
        return await self.x.position_deg(), await self.y.position_deg()

    async def wait_until_idle(self, timeout_s: float) -> float:
        return max(
            await asyncio.gather(
                self.x.wait_until_idle(timeout_s), self.y.wait_until_idle(timeout_s)
            )
        )

    async def stop(self) -> None:
        await self.x.stop()
        await self.y.stop()

    async def home(self) -> None:
        await self.x.home()
        await self.y.home()
