"""``mbmon sim`` as a process: help text, address line, a real client, clean stop on signals."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def mbmon(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mbmon", *args], capture_output=True, text=True, env=ENV, timeout=60
    )


def test_help_says_it_is_a_test_partner_not_a_robot_simulator() -> None:
    out = mbmon("sim", "--help")
    assert out.returncode == 0
    text = " ".join(out.stdout.split())
    assert "test partner and a teaching tool, NOT a robot simulator" in text
    assert "127.0.0.1:1502" in text
    assert "sim" in mbmon("--help").stdout


@pytest.mark.parametrize(
    "args",
    [["--listen", "nowhere"], ["--listen", "127.0.0.1:70000"], ["--unit", "0"],
     ["--unit", "248"], ["--parity", "X"], ["--stopbits", "3"], ["--baud", "fast"]],
)  # fmt: skip
def test_bad_options_are_usage_errors(args: list[str]) -> None:
    out = mbmon("sim", *args)
    assert out.returncode == 2 and "error" in out.stderr and "Traceback" not in out.stderr


def test_a_missing_serial_port_is_a_clear_error() -> None:
    out = mbmon("sim", "--serial", "/nonexistent/ttyX")
    assert out.returncode == 1
    assert "Traceback" not in out.stderr and "Could not start listen" not in out.stderr
    assert "cannot open serial port /nonexistent/ttyX: No such file or directory" in out.stderr


def test_a_file_that_is_not_a_serial_port_is_named_as_such() -> None:
    out = mbmon("sim", "--serial", "/dev/null")
    assert out.returncode == 1
    assert "cannot open serial port /dev/null: not a serial port" in out.stderr


@pytest.mark.parametrize("command", ["sim", "proxy"])
def test_a_port_in_use_is_named_as_such_by_sim_and_proxy_alike(command: str) -> None:
    import socket

    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        extra = ["--upstream", "127.0.0.1:1"] if command == "proxy" else []
        out = mbmon(command, *extra, "--listen", f"127.0.0.1:{port}")
    assert out.returncode == 1
    assert "Could not start listen" not in out.stderr and "Traceback" not in out.stderr
    assert (
        f"cannot listen on 127.0.0.1:{port}: Address already in use (another program listens"
        in out.stderr
    )


def test_the_words_for_a_privileged_port_and_other_reasons() -> None:
    import errno

    from mbmon.commands.common import listen_error, serial_open_error

    denied = PermissionError(errno.EACCES, "Permission denied")
    text = listen_error("0.0.0.0:502", denied, 502)
    assert text.startswith(
        "cannot listen on 0.0.0.0:502: Permission denied (port 502 is privileged"
    )
    assert "1024" in text
    assert listen_error("0.0.0.0:5020", denied, 5020) == (
        "cannot listen on 0.0.0.0:5020: Permission denied"
    )
    assert "dialout" in serial_open_error("/dev/ttyUSB0", denied)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_serves_on_loopback_prints_its_address_and_stops_cleanly(sig: signal.Signals) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "sim", "--listen", "127.0.0.1:0", "--unit", "5"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
    )
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        m = re.fullmatch(
            r"mbmon sim: HRSS robot, unit 5, Modbus/TCP on 127\.0\.0\.1:(\d+)\n", first
        )
        assert m, first
        assert "not a robot simulator" in proc.stdout.readline()
        client = ModbusTcpClient("127.0.0.1", port=int(m.group(1)), timeout=3, retries=0)
        assert client.connect()
        try:
            assert client.read_input_registers(100, count=1, device_id=5).registers == [100]
            client.write_registers(201, [104, 6], device_id=5)  # Set Current BASE[6]
            client.write_registers(200, [1], device_id=5)
            assert client.read_input_registers(200, count=1, device_id=5).registers == [1]
        finally:
            client.close()
        line = proc.stdout.readline()
        assert "execute" in line and "success: Set Current BASE[6]" in line
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert out.endswith("mbmon sim: stopped\n")
    assert "Traceback" not in err


def test_importing_mbmon_sim_loads_no_pymodbus_serial_or_scapy() -> None:
    code = (
        "import sys, mbmon.sim, mbmon.cli; mbmon.cli.build_parser(); "
        "bad = [m for m in ('scapy', 'serial', 'pymodbus') if m in sys.modules]; "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV)
    assert out.returncode == 0, out.stdout + out.stderr


def test_sim_sniff_and_proxy_default_to_one_baud_rate() -> None:
    from mbmon.cli import build_parser
    from mbmon.sim.server import SimServer
    from mbmon.sources import DEFAULT_BAUD
    from mbmon.sources.serial import SerialSettings

    parser = build_parser()
    sim = parser.parse_args(["sim", "--serial", "/dev/ttyX"])
    proxy = parser.parse_args(["proxy", "--upstream-serial", "/dev/ttyX"])
    assert sim.baud == proxy.baud == SerialSettings().baudrate == DEFAULT_BAUD == 115200
    assert SimServer(serial="/dev/ttyX").baudrate == DEFAULT_BAUD
    for command in ("sim", "sniff", "proxy"):  # one builder: one help
        assert f"baud rate ({DEFAULT_BAUD})" in mbmon(command, "--help").stdout
