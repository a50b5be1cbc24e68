"""A bench as the daemon owns it: its drivers, the latest readings and stage pose, and who holds it.

Readings come from the drivers' own streams (automatic output, polling), the stage pose from a
poller here, so `/tilt` and `/devices` read memory and never wait behind a move. One job holds a
bench at a time; `stop()` reaches the controller at once whatever holds it.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import logging
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import Protocol, TypeVar

from service.bench.settled import StandSettling
from service.clock import Clock
from service.instruments import controller
from service.instruments.base import DeviceIdentity, Reading
from service.instruments.bench_config import BenchConfig
from service.instruments.drivers import IDLE_POLL_MISSES
from service.instruments.transport import DeviceError, DeviceRefused, DeviceTimeout
from service.instruments.wiring import BenchDevices, open_bench

log = logging.getLogger("tiltlab.bench")
T = TypeVar("T")

STAGE_POLL_S = 0.1  # bench seconds between pose queries
STAGE_POLL_MIN_S = 0.05  # real seconds: a sped-up bench's pose is not asked more often than this
# bench seconds between temperature queries of sensors whose frames carry none
TEMPERATURE_POLL_S = 10.0
SENSOR_ROLES = (
    "reference_sensor",
    "measurement_sensor",
    "triaxial_sensor",
    "turntable_sensor",
    "adc_sensor",
)
MOTION_ROLES = ("stage", "rotary_table")


class BenchBusy(Exception):
    """A job or a levelling holds the bench."""


class DeviceNotAnswering(Exception):
    """A device a request needs does not answer; the message names the role and port."""


class StageNotHomed(DeviceError):
    """The stage controller has not found its reference switches since power-up and refuses
    moves."""


class MotionStopped(DeviceError):
    """A move or homing ended by `POST /stage/stop` (or a job's stop) before it reached its end: a
    conflict with another request, not a device fault."""


# the controller's refusal, as the driver names it
NOT_HOMED = controller.ERROR_NAMES[controller.ERR_NOT_HOMED]


def _not_homed(bench: str, exc: DeviceRefused) -> Exception:
    if NOT_HOMED in str(exc):
        return StageNotHomed(
            f"bench {bench!r}: the stage is not homed (its controller refuses moves until it has"
            f" found its reference switches); home it first (POST /stage/home): {exc}"
        )
    return exc


class Hold(StrEnum):
    """What holds a bench: one at a time."""

    JOB = "job"
    JOB_RESUMING = "job resuming"
    JOB_BEING_CREATED = "job being created"
    STAGE_MOVE = "stage move"
    LEVELLING = "levelling"
    HOMING = "homing"


_HOLD_TEXT = {
    Hold.JOB_BEING_CREATED: "a job being created",
    Hold.STAGE_MOVE: "a stage move",
    Hold.LEVELLING: "levelling",
    Hold.HOMING: "homing",
}


@dataclass(frozen=True)
class BenchHold:
    """Who holds a bench; its text ("job 12", "levelling") is what GET /benches and a 409 name."""

    kind: Hold
    job_id: int | None = None

    def __str__(self) -> str:
        if self.kind is Hold.JOB:
            return f"job {self.job_id}"
        if self.kind is Hold.JOB_RESUMING:
            return f"job {self.job_id} (resuming)"
        return _HOLD_TEXT[self.kind]

    @classmethod
    def job(cls, job_id: int) -> BenchHold:
        return cls(Hold.JOB, job_id)


async def polled(query: Callable[[], Awaitable[T]], misses: int = IDLE_POLL_MISSES) -> T:
    """A poll of a device's state or position, asked again when its answer is lost on the line:
    only `misses` unanswered in a row raise (a single lost answer under load is not a lost
    device)."""
    for attempt in range(1, misses + 1):
        try:
            return await query()
        except DeviceTimeout:
            if attempt == misses:
                raise
    raise AssertionError("unreachable")


@dataclass
class StagePose:
    x_deg: float | None = None
    y_deg: float | None = None
    moving: bool = False
    time_utc: dt.datetime | None = None
    # Bench seconds (the bench clock's) since which the stage has stood where it stands: the
    # earliest reading an averaged tilt may take (None while it moves, or before its pose was first
    # asked)
    still_since_bench_s: float | None = None
    # Sign of the last move of each axis (the side backlash is taken up on).
    dir_x: float = 1.0
    dir_y: float = 1.0


class SimulatedBench(Protocol):
    """The simulated bench behind a bench's ports: closed with it; its world names the scenarios it
    runs."""

    @property
    def world(self) -> object: ...

    def close(self) -> None: ...


class BenchRuntime:
    def __init__(
        self,
        config: BenchConfig,
        clock: Clock,
        devices: BenchDevices | None = None,
        sim: SimulatedBench | None = None,
    ) -> None:
        self.config = config
        self.name = config.name
        self.kind = config.kind
        self.clock = clock
        self.devices = devices or open_bench(config, clock)
        self.sim = sim  # the simulated bench behind the ports, if any (its truth is for tests)
        self.pose = StagePose()
        self.rotary_deg: float | None = None
        # Bench seconds at which the last motion (a move, homing, a turn) was found at its end by
        # the controller: when it stopped, however late the daemon read the answer (the boundary of
        # a job's moving and settling)
        self.stopped_bench_s: float = clock.monotonic()
        # when the readings at the present stand settled (averaged tilt)
        self.stand_settling = StandSettling()
        self.identities: dict[str, DeviceIdentity] = {}
        self.device_ids: dict[str, int] = {}
        self.bench_id: int | None = None
        self.holder: BenchHold | None = None
        self.stop_requested = asyncio.Event()
        self._stage_task: asyncio.Task[None] | None = None
        self._temperature_task: asyncio.Task[None] | None = None
        self._motion_lock = asyncio.Lock()

    # ------------------------------------------------------------ life

    async def start(self) -> None:
        await self.devices.start()
        for role in self.devices:
            with contextlib.suppress(DeviceError, asyncio.TimeoutError):
                self.identities[role] = await asyncio.wait_for(self.devices[role].identify(), 5.0)
        loop = asyncio.get_running_loop()
        self._stage_task = loop.create_task(self._poll_motion())
        self._temperature_task = loop.create_task(self._poll_temperatures())

    async def close(self) -> None:
        for task in (self._stage_task, self._temperature_task):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
        await self.devices.close()
        if self.sim is not None:
            self.sim.close()

    def roles(self) -> list[str]:
        return list(self.devices)

    def port_of(self, role: str) -> str:
        return self.config.role(role).where

    # ------------------------------------------------------------ latest values, no I/O

    def latest(self, role: str) -> Reading | None:
        return self.devices.sensor(role).latest() if role in self.devices else None

    def stopped_after(self, began_s: float) -> float | None:
        """When the last motion stopped, if that was at or after `began_s` (the end of a move begun
        then); None otherwise: an older stop mark is not this move's end, and readings since it
        would hold the move."""
        return self.stopped_bench_s if self.stopped_bench_s >= began_s else None

    def readings_after(self, role: str, bench_s: float) -> list[Reading]:
        """Every kept reading of the role stamped after `bench_s`, oldest first (the latest only,
        for a device that keeps no history)."""
        if role not in self.devices:
            return []
        return self.devices.sensor(role).readings_after(bench_s)

    def output_interval_s(self, role: str) -> float:
        """How often the role's readings arrive (bench seconds): what `stale` is judged against."""
        spec = self.config.role(role)
        rate = getattr(spec, "output_rate_hz", None)
        if isinstance(rate, int | float) and rate > 0:
            return 1.0 / rate
        if rate == "continuous":
            return 0.01
        poll = getattr(spec, "poll_rate_hz", None)
        return 1.0 / poll if poll else 1.0

    def state(self) -> str:
        states = [statu.state for statu in self.devices.status()]
        if "failed" in states:
            return "degraded"
        if "reconnecting" in states:
            return "connecting"
        return "busy" if self.holder else "ready"

    async def _poll_motion(self) -> None:
        while True:
            with contextlib.suppress(DeviceError):
                await self.refresh_pose()
            # bench time, but never more than 20 times a real second: moves and jobs ask the pose
            # themselves, this only keeps /tilt's and /devices' pose of an idle bench current
            await asyncio.sleep(max(self.clock.real_seconds(STAGE_POLL_S), STAGE_POLL_MIN_S))

    async def _poll_temperatures(self) -> None:
        """Binary inclinometers send angles only; their temperature (0x06) is asked now and then, so
        GET /tilt and the streams carry one between jobs too (a job asks at every point)."""
        drivers = [
            sensor
            for sensor in (
                self.devices.temperature_on_request(role)
                for role in ("reference_sensor", "measurement_sensor", "triaxial_sensor")
            )
            if sensor is not None
        ]
        while drivers:
            for driver in drivers:
                if driver.status.state == "connected" and driver.answers_temperature:
                    with contextlib.suppress(DeviceError):
                        await driver.read_temperature()
            # bench time (a sped-up bench is asked more often), but never more than once a real
            # second
            await asyncio.sleep(max(self.clock.real_seconds(TEMPERATURE_POLL_S), 1.0))

    async def refresh_pose(self) -> None:
        if "stage" in self.devices:
            stage = self.devices.stage_axes()
            x, y = await polled(stage.position_deg)
            # a stage that stood at the last poll and has not moved since still stands: its states
            # are asked only when something moved (a move's end, a jog) or motion was under way
            moving = False
            changed = self.pose.moving or (x, y) != (self.pose.x_deg, self.pose.y_deg)
            if changed:
                moving = "moving" in (await polled(stage.x.state), await polled(stage.y.state))
            if moving:
                self.pose.still_since_bench_s = None
            elif changed or self.pose.still_since_bench_s is None:
                # it stands: since now, as far as is known
                self.pose.still_since_bench_s = self.clock.monotonic()
            self.pose.x_deg, self.pose.y_deg, self.pose.moving = x, y, moving
            self.pose.time_utc = self.clock.utc()
        if "rotary_table" in self.devices:
            self.rotary_deg = await polled(self.devices.axis("rotary_table").position_deg)

    # ------------------------------------------------------------ ownership and motion

    @contextlib.asynccontextmanager
    async def hold(self, holder: BenchHold) -> AsyncIterator[None]:
        if self.holder is not None:
            raise BenchBusy(f"bench {self.name!r} is held by {self.holder}")
        self.holder = holder
        self.stop_requested.clear()
        try:
            yield
        finally:
            self.holder = None

    async def sync(self, roles: tuple[str, ...]) -> float:
        """A mark after which every reading of `roles` was made after this call (bench seconds)."""
        marks = []
        for role in roles:
            self.require(role)
            marks.append(await self.devices.sensor(role).sync())
        return max(marks, default=self.clock.monotonic())

    def require(self, role: str) -> None:
        if role not in self.devices:
            raise DeviceNotAnswering(f"bench {self.name!r} has no {role}")
        st = self.devices[role].status
        if st.state != "connected":
            raise DeviceNotAnswering(
                f"{role} on {st.port} is {st.state}" + (f": {st.error}" if st.error else "")
            )

    async def move_stage(
        self, x_deg: float, y_deg: float, *, timeout_s: float = 600.0, passing: bool = False
    ) -> tuple[float, float]:
        """Move both stages and wait until they stand; returns the position reached (degrees).
        `passing`: a position only passed through (an approach from one side), never read at: the
        sensors are not synchronised to its stand, which saves a sensor output interval a move."""
        self.require("stage")
        stage = self.devices.stage_axes()
        async with self._motion_lock:
            if self.pose.x_deg is not None:
                if x_deg != self.pose.x_deg:
                    self.pose.dir_x = 1.0 if x_deg > self.pose.x_deg else -1.0
                if self.pose.y_deg is not None and y_deg != self.pose.y_deg:
                    self.pose.dir_y = 1.0 if y_deg > self.pose.y_deg else -1.0
            try:
                await stage.move_to_deg(x_deg, y_deg)
            except DeviceRefused as exc:
                raise _not_homed(self.name, exc) from exc
            self.pose.moving, self.pose.still_since_bench_s = True, None
            self.stopped_bench_s = await self._until_idle(stage.wait_until_idle, timeout_s)
            await self.refresh_pose()
            # a position passed through is no stand to average readings over
            self.pose.still_since_bench_s = None if passing else await self._stood_mark()
            return self._stage_position()

    async def _stood_mark(self) -> float:
        """Bench seconds after which every reading of the tilt sensors was made with the stage
        standing: a sync mark, since a lagging reader may still hand out readings made during the
        move (the present time where no sensor answers)."""
        roles = tuple(
            role
            for role in ("measurement_sensor", "reference_sensor")
            if role in self.devices and self.devices[role].status.state == "connected"
        )
        with contextlib.suppress(DeviceError):
            return await self.sync(roles) if roles else self.clock.monotonic()
        return self.clock.monotonic()

    async def _until_idle(
        self, wait: Callable[[float], Awaitable[float]], timeout_s: float
    ) -> float:
        """Wait for motion to end; a stop requested meanwhile is MotionStopped, whatever state the
        stop left the axes in (a homing stopped half way ends in the controller's error state).
        Returns the bench time the controller was found standing."""
        try:
            stopped = await wait(timeout_s)
        except DeviceError:
            self._check_stopped()
            raise
        self._check_stopped()
        return stopped

    def _stage_position(self) -> tuple[float, float]:
        x, y = self.pose.x_deg, self.pose.y_deg
        # refresh_pose has just read both axes from the controller
        assert x is not None and y is not None
        return x, y

    async def home_stage(self, *, timeout_s: float = 600.0) -> tuple[float, float]:
        """Home both stage axes (each finds its reference switch; its position becomes 0) and wait
        until they stand; returns the position reached (degrees)."""
        self.require("stage")
        stage = self.devices.stage_axes()
        async with self._motion_lock:
            await stage.home()
            self.pose.moving, self.pose.still_since_bench_s = True, None
            self.stopped_bench_s = await self._until_idle(stage.wait_until_idle, timeout_s)
            await self.refresh_pose()
            self.pose.still_since_bench_s = await self._stood_mark()
            return self._stage_position()

    async def move_rotary(self, angle_deg: float, *, timeout_s: float = 600.0) -> float:
        self.require("rotary_table")
        table = self.devices.axis("rotary_table")
        async with self._motion_lock:
            await table.move_to_deg(angle_deg)
            self.stopped_bench_s = await self._until_idle(table.wait_until_idle, timeout_s)
            self.rotary_deg = await table.position_deg()
            return self.rotary_deg

    def _check_stopped(self) -> None:
        if self.stop_requested.is_set():
            raise MotionStopped(
                f"bench {self.name!r}: motion stopped by request (POST /stage/stop) before it"
                " reached its end"
            )

    async def stop(self) -> None:
        """Stop every axis now, whatever holds the bench (the motion lock is not waited for)."""
        self.stop_requested.set()
        for role in MOTION_ROLES:
            if role in self.devices:
                await (
                    self.devices.stage_axes(role) if role == "stage" else self.devices.axis(role)
                ).stop()
