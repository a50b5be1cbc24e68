"""The in-memory line stands in for a pty: pyserial opens its URL, bytes pass both ways in order,
a pulled cable fails the open end and the name until it is plugged again."""

from __future__ import annotations

import pytest
import serial

from service.instruments.sim.loopback import LineGone, MemoryLine, register_handler


def _open(url: str) -> serial.SerialBase:
    register_handler()
    return serial.serial_for_url(url, baudrate=9600, timeout=0.05)


def test_bytes_pass_both_ways_in_order_and_a_read_returns_what_came_within_its_timeout():
    line = MemoryLine("test")
    try:
        host = _open(line.url)
        host.write(b"ID?\r")
        assert line.read_instrument(1.0) == b"ID?\r"
        assert line.write_instrument(b"ab") == 2
        line.write_instrument(b"cd")
        assert host.in_waiting == 4
        assert host.read(3) == b"abc"
        assert host.read(3) == b"d"  # what came within the timeout
        assert host.read(1) == b""
        host.close()
    finally:
        line.close()


def test_opening_drops_what_came_before_as_pyserial_does_on_a_device():
    line = MemoryLine("test")
    try:
        line.write_instrument(b"stale")
        host = _open(line.url)
        assert host.read(5) == b""
        line.write_instrument(b"fresh")
        assert host.read(5) == b"fresh"
        host.close()
    finally:
        line.close()


def test_one_owner_at_a_time():
    line = MemoryLine("test")
    try:
        first = _open(line.url)
        with pytest.raises(serial.SerialException, match="open already"):
            _open(line.url)
        first.close()
        _open(line.url).close()
    finally:
        line.close()


def test_a_pulled_cable_fails_the_open_end_and_the_name_until_plugged_again():
    line = MemoryLine("test")
    try:
        host = _open(line.url)
        line.unplug()
        with pytest.raises(serial.SerialException):
            host.read(1)
        with pytest.raises(LineGone, match="no such device"):
            _open(line.url)
        assert line.write_instrument(b"lost") == 4  # into a pulled cable: gone
        line.plug()
        again = _open(line.url)
        assert again.read(1) == b""
        again.close()
    finally:
        line.close()


def test_a_name_that_is_no_line_is_refused():
    with pytest.raises(serial.SerialException, match="no simulated instrument"):
        _open("simloop://nothing-here-1")
