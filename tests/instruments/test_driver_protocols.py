"""Every driver class is what its role's protocol says: declared, found by isinstance, and with the
protocol's signatures (parameter names, kinds and defaults; extra parameters only with a
default)."""

from __future__ import annotations

import inspect

import pytest

from service.clock import Clock
from service.instruments import base
from service.instruments.drivers import (
    AdcSensor,
    BinaryInclinometer,
    ControllerAxis,
    Rs485Inclinometer,
    Rs485Thermohygrometer,
    StageController,
    TriaxialModule,
)
from service.instruments.framing import Parsed, ParseStats
from service.instruments.transport import SerialPort


def _port() -> SerialPort:
    return SerialPort("nowhere", lambda b: Parsed([], b, ParseStats()), baud=9600)  # never started


def _axis(n: int = 3) -> ControllerAxis:
    return ControllerAxis("rotary_table", _port(), Clock(1.0), 0.5, n, 0.001)


def _drivers() -> list[tuple[object, type]]:
    port, c = _port(), Clock(1.0)
    return [
        (BinaryInclinometer("reference_sensor", port, c, 0.5, 0), base.TiltSensor),
        (BinaryInclinometer("reference_sensor", port, c, 0.5, 0), base.TemperatureOnRequest),
        (TriaxialModule("triaxial_sensor", port, c, 0.5, 0), base.TriaxialSensor),
        (TriaxialModule("triaxial_sensor", port, c, 0.5, 0), base.TemperatureOnRequest),
        (Rs485Inclinometer("turntable_sensor", port, c, 0.5, 1), base.TiltSensor),
        (AdcSensor("adc_sensor", port, c, 0.5), base.AnalogSensor),
        (
            Rs485Thermohygrometer("ambient_sensor", port, c, 0.5, 2, 1.0, 0.1, 2.0),
            base.AmbientSensor,
        ),
        (_axis(), base.MotionAxis),
        (StageController("stage", _axis(1), _axis(2)), base.TwoAxisStage),
    ]


CASES = _drivers()


def _members(protocol: type) -> dict[str, object]:
    """The protocol's own and inherited members (not those of Protocol/Generic/object)."""
    out: dict[str, object] = {}
    for klass in reversed(protocol.__mro__):
        if klass in (object,) or klass.__module__ == "typing":
            continue
        for name in getattr(klass, "__annotations__", {}):
            out.setdefault(name, None)
        for name, value in vars(klass).items():
            if not name.startswith("_"):
                out[name] = value
    return out


@pytest.mark.parametrize(
    ("driver", "protocol"), CASES, ids=[f"{type(d).__name__}-{p.__name__}" for d, p in CASES]
)
def test_driver_declares_and_satisfies_its_protocol(driver, protocol):
    # (issubclass refuses protocols with data members: the class's bases are read instead)
    assert protocol in type(driver).__mro__, (
        f"{type(driver).__name__} does not name {protocol.__name__} as a base"
    )
    assert isinstance(driver, protocol)
    assert isinstance(driver, base.Driver)
    for name, member in _members(protocol).items():
        assert hasattr(driver, name), f"{type(driver).__name__} lacks {name}"
        if isinstance(member, property):
            assert isinstance(
                inspect.getattr_static(type(driver), name, None), property
            ) or name in vars(driver), name
            continue
        if not inspect.isfunction(member):
            continue  # a data member: present is what the protocol asks
        implemented = getattr(type(driver), name)
        assert inspect.iscoroutinefunction(implemented) == inspect.iscoroutinefunction(member), (
            f"{type(driver).__name__}.{name}: async in one, not in the other"
        )
        wanted = list(inspect.signature(member).parameters.values())
        got = list(inspect.signature(implemented).parameters.values())
        assert [(p.name, p.kind, p.default) for p in got[: len(wanted)]] == [
            (p.name, p.kind, p.default) for p in wanted
        ], f"{type(driver).__name__}.{name}{inspect.signature(implemented)}"
        extra = got[len(wanted) :]
        assert all(
            p.default is not inspect.Parameter.empty or p.kind in (p.VAR_KEYWORD, p.VAR_POSITIONAL)
            for p in extra
        ), f"{type(driver).__name__}.{name}: extra parameters without a default"
        assert str(inspect.signature(implemented).return_annotation) == str(
            inspect.signature(member).return_annotation
        ), f"{type(driver).__name__}.{name}: return type"


def test_every_protocol_member_is_checked():
    """A protocol that grows a member is held to it by the test above (nothing is skipped
    silently)."""
    assert {
        "latest",
        "readings_after",
        "sync",
        "stop_polling",
        "status",
        "identify",
        "role",
    } <= set(_members(base.TiltSensor))
    assert {"x", "y", "move_to_deg", "wait_until_idle"} <= set(_members(base.TwoAxisStage))
