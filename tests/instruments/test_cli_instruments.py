"""`tiltlab sim` and `tiltlab devices`: a printed configuration that works, and one line per role
that does not answer as configured (wrong path, silent port, wrong family, wrong address), exit
2."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from service.cli import main
from tests.helpers.processes import spawn

# the ports are pseudo-terminals: device paths, as the command line and adapters name them
pytestmark = pytest.mark.pty


def _config(tmp_path, sim, **override) -> str:
    """The simulator's configuration with some roles' tables replaced."""
    text = sim.toml
    for role, table in override.items():
        head = f"[benches.{sim.bench_name}.roles.{role}]"
        start = text.index(head)
        end = text.find("\n[", start + 1)
        end = len(text) if end < 0 else end
        text = text[:start] + head + "\n" + table + "\n" + text[end:]
    path = tmp_path / "bench.toml"
    path.write_text(text)
    return str(path)


def test_devices_lists_what_answered(tmp_path, stage_sim, capsys):
    assert main(["devices", "--config", _config(tmp_path, stage_sim)]) == 0
    out = capsys.readouterr().out
    for role in ("reference_sensor", "measurement_sensor", "stage", "adc_sensor"):
        assert role in out and stage_sim.port_path(role) in out
    assert "SC-200SIM" in out and "ADC12-SIM" in out


def test_wrong_port_path(tmp_path, stage_sim, capsys):
    missing = tmp_path / "no-such-port"
    cfg = _config(tmp_path, stage_sim, reference_sensor=f'port = "{missing}"')
    assert main(["devices", "--config", cfg]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert f"role reference_sensor on port {missing}: cannot be opened" in err[0]
    assert "expected a 0x68 binary inclinometer at address 0x00" in err[0]


def test_silent_port(tmp_path, stage_sim, capsys):
    master, slave = os.openpty()  # a port that exists and answers nothing
    try:
        path = os.ttyname(slave)
        cfg = _config(tmp_path, stage_sim, adc_sensor=f'port = "{path}"\ntimeout_s = 0.3')
        assert main(["devices", "--config", cfg]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [
            (
                f"tiltlab devices: error: role adc_sensor on port {path}: no answer within 0.3 s; "
                "expected an ADC answering ID?"
            )
        ]
    finally:
        os.close(master)
        os.close(slave)


def test_wrong_family(tmp_path, stage_sim, capsys):
    """The stage role pointed at an inclinometer: its frames are not the controller's protocol."""
    cfg = _config(
        tmp_path,
        stage_sim,
        stage=f'port = "{stage_sim.port_path("reference_sensor")}"\ntimeout_s = 0.3',
        reference_sensor=f'port = "{stage_sim.port_path("stage")}"\ntimeout_s = 0.3',
    )
    assert main(["devices", "--config", cfg]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2
    ref = next(e for e in err if "role reference_sensor" in e)
    stage = next(e for e in err if "role stage" in e)
    assert (
        f"port {stage_sim.port_path('stage')}: no answer" in ref
        and "expected a 0x68 binary inclinometer" in ref
    )
    assert (
        f"port {stage_sim.port_path('reference_sensor')}: sent " in stage
        and "in another protocol" in stage
    )
    assert "expected a stage controller answering on axes 1 and 2" in stage


def test_wrong_address(tmp_path, stage_sim, capsys):
    port = stage_sim.port_path("measurement_sensor")
    cfg = _config(
        tmp_path, stage_sim, measurement_sensor=f'port = "{port}"\naddress = 5\ntimeout_s = 0.3'
    )
    assert main(["devices", "--config", cfg]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        (
            f"tiltlab devices: error: role measurement_sensor on port {port}: answered from "
            "address 0x00; expected a 0x68 binary inclinometer at address 0x05"
        )
    ]


def test_wrong_bus_address(tmp_path, rotary_sim, capsys):
    port = rotary_sim.port_path("turntable_sensor")
    cfg = _config(
        tmp_path, rotary_sim, turntable_sensor=f'port = "{port}"\naddress = "2F"\ntimeout_s = 0.3'
    )
    assert main(["devices", "--config", cfg]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        (
            f"tiltlab devices: error: role turntable_sensor on port {port}: no answer within 0.3 "
            "s; expected an RS-485 inclinometer at address 2F"
        )
    ]


def test_a_configuration_that_is_not_one(tmp_path, capsys):
    bad = tmp_path / "bench.toml"
    bad.write_text('[benches.a]\nkind = "stage"\n')
    assert main(["devices", "--config", str(bad)]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_sim_command_prints_ports_and_a_configuration_devices_accepts(tmp_path):
    """The real console script in its own process, as a lab would run it."""
    folder = tmp_path / "ports"
    out = tmp_path / "sim.toml"
    proc = spawn(
        [
            sys.executable,
            "-m",
            "service",
            "sim",
            "--bench",
            "rotary",
            "--scenario",
            "seed004",
            "--speed",
            "10",
            "--dir",
            str(folder),
            "--out",
            str(out),
            "--duration",
            "60",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        lines = []
        while not any(line.startswith("bench configuration:") for line in lines):
            line = proc.stdout.readline()
            assert line, proc.stderr.read()
            lines.append(line)
        assert any(
            line.startswith("rotary_table") and str(folder / "rotary_table") in line
            for line in lines
        )
        assert out.is_file()
        done = subprocess.run(
            [sys.executable, "-m", "service", "devices", "--config", str(out)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert done.returncode == 0, done.stderr
        assert (
            "RT-360SIM" in done.stdout
            and "NV-210SIM" in done.stdout
            and "triaxial module" in done.stdout
        )
    finally:
        proc.terminate()
        assert proc.wait(timeout=20) == 0


@pytest.mark.parametrize(
    "argv, message",
    [
        (["sim", "--speed", "0"], "speed factor"),
        (
            ["sim", "--bench", "rotary", "--scenario", "seed000", "--duration", "1"],
            "rotary bench needs",
        ),
        (["sim", "--scenario", "no-such-scenario", "--duration", "1"], "no-such-scenario"),
    ],
)
def test_sim_refuses_bad_input(argv, message, capsys, tmp_path):
    try:
        code = main(argv + ["--dir", str(tmp_path / "p")])
    except SystemExit as exc:  # argparse refusals
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
