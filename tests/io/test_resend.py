"""``replay --to``: the comparison (byte tables) and re-sending logs recorded from
``mbmon sim`` to a live sim (real sockets, real MCAP), reads only unless --writes."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import simlog

from mbmon.io.emulate import EmulatorServer, RegisterImage
from mbmon.io.exchanges import recorded_exchanges
from mbmon.io.mcap.reader import McapLog
from mbmon.io.resend import LiveClient, LiveError, changes_server, compare, resend
from mbmon.protocol.pdu import decode_pdu

# --------------------------------------------------------------------------- compare


def req(hex_: str) -> Any:
    return decode_pdu(bytes.fromhex(hex_), response=False)


def resp(hex_: str, request: Any) -> Any:
    return decode_pdu(bytes.fromhex(hex_), response=True, request=request)


def test_compare_registers_address_by_address() -> None:
    r = req("0300c80003")
    assert compare(r, resp("0306000100020003", r), resp("0306000100020003", r)) == []
    assert compare(r, resp("0306000100020003", r), resp("0306000100090004", r)) == [
        "2 holding registers differ: 201 recorded 2, live 9; 202 recorded 3, live 4"
    ]
    i = req("04012c0001")
    assert compare(i, resp("04020005", i), resp("04020006", i)) == [
        "1 input register differs: 300 recorded 5, live 6"
    ]


def test_compare_bits_trimmed_to_the_request() -> None:
    r = req("0100000003")
    # the padding bits past the count are not values
    assert compare(r, resp("010105", r), resp("0101f5", r)) == []
    assert compare(r, resp("010105", r), resp("010104", r)) == [
        "1 coil differs: 0 recorded 1, live 0"
    ]
    d = req("0200000002")
    assert compare(d, resp("020101", d), resp("020102", d)) == [
        "2 discrete inputs differ: 0 recorded 1, live 0; 1 recorded 0, live 1"
    ]


def test_compare_exceptions_missing_answers_and_bytes() -> None:
    r = req("0300c80001")
    values, exc2, exc4 = resp("03020001", r), resp("8302", r), resp("8304", r)
    assert compare(r, exc2, exc2) == []
    assert compare(r, exc2, exc4) == [
        "recorded exception 02 (Illegal Data Address), live exception 04 (Server Device Failure)"
    ]
    assert compare(r, values, exc2) == ["recorded values, live exception 02 (Illegal Data Address)"]
    assert compare(r, None, values) == ["recorded no answer, live values"]
    assert compare(r, values, None) == ["recorded values, live no answer"]
    assert compare(r, None, None) == []
    w = req("0600c80001")
    assert compare(w, resp("0600c80001", w), resp("0600c80002", w)) == [
        "recorded 06 00 C8 00 01, live 06 00 C8 00 02"
    ]


def test_compare_lists_at_most_eight_differences() -> None:
    r = req("030000000a")
    rec = resp("0314" + "0000" * 10, r)
    live = resp("0314" + "0001" * 10, r)
    (line,) = compare(r, rec, live)
    assert line.startswith("10 holding registers differ: 0 recorded 0, live 1;")
    assert line.endswith("; ... 2 more")


def test_changes_server() -> None:
    writes = ("0600c80001", "1000c8000102000a", "050000ff00", "0f000000010101",
              "16000a00f00025", "17000a0001000b0001020007", "0800010000", "08000a0000")  # fmt: skip
    for pdu in writes:
        assert changes_server(req(pdu)), pdu
    for pdu in ("0300c80001", "0400000001", "0100000001", "0200000001", "0800000102", "11"):
        assert not changes_server(req(pdu)), pdu


# --------------------------------------------------------------------------- live servers


@pytest.fixture(scope="module")
def sim_logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``reads`` and ``writes``: a log each, recorded from a fresh sim through the proxy."""
    from mbmon.sim.server import SimServer

    tmp = tmp_path_factory.mktemp("resendlogs")
    out: dict[str, Path] = {}
    for name, traffic in (("reads", simlog.reads), ("writes", simlog.writes_then_reads)):
        with SimServer() as sim:
            out[name] = tmp / f"{name}.mcap"
            simlog.record(sim.port, out[name], traffic)
    return out


@contextmanager
def fresh_sim() -> Iterator[Any]:
    from mbmon.sim.server import SimServer

    with SimServer() as sim:
        yield sim


def test_to_a_fresh_sim_reports_no_differences(sim_logs: dict[str, Path]) -> None:
    with fresh_sim() as sim:
        done = simlog.replay(str(sim_logs["reads"]), "--to", f"127.0.0.1:{sim.port}")
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"re-sent 10 recorded requests to 127.0.0.1:{sim.port}: 10 answered as recorded, " \
        "0 differently (0 not answered live)" in done.stdout  # fmt: skip
    assert "writes not sent" not in done.stdout


def test_to_reports_the_registers_that_differ_after_the_sim_changed(
    sim_logs: dict[str, Path],
) -> None:
    with fresh_sim() as sim:
        c = simlog.client(sim.port)
        try:
            c.write_register(203, 9)
            c.write_coil(5, True)
        finally:
            c.close()
        sim.call(lambda robot, _now: robot.joints.__setitem__(0, 45.0))  # move A1 to 45°
        done = simlog.replay(str(sim_logs["reads"]), "--to", f"127.0.0.1:{sim.port}")
    assert done.returncode == 3, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    assert any(
        "unit 1 03 Read Holding Registers 201..210: 1 holding register differs: "
        "203 recorded 0, live 9" in line
        for line in lines
    ), done.stdout
    assert any(
        "unit 1 01 Read Coils 0..15: 1 coil differs: 5 recorded 0, live 1" in line for line in lines
    ), done.stdout
    a1 = [line for line in lines if "04 Read Input Registers 300..311" in line]
    assert len(a1) == 1 and "300 recorded 0, live " in a1[0], done.stdout
    assert "10 recorded requests" in done.stdout and "7 answered as recorded, 3 differently" \
        in done.stdout  # fmt: skip


def _sim_holding(sim: Any, address: int) -> int:
    return int(sim.call(lambda robot, _now: robot.holding[address]))


def test_writes_are_not_sent_without_writes(sim_logs: dict[str, Path]) -> None:
    with fresh_sim() as sim:
        done = simlog.replay(str(sim_logs["writes"]), "--to", f"127.0.0.1:{sim.port}")
        untouched = [_sim_holding(sim, a) for a in (201, 202, 203, 300)]
        coils = sim.call(lambda robot, _now: robot.coils[3:7])
    assert untouched == [0, 0, 0, 0]
    assert coils == [0, 0, 0, 0]
    assert "4 recorded writes not sent (they can move a robot: --writes sends them)" in done.stdout
    assert "re-sent 6 recorded requests" in done.stdout
    assert done.returncode == 3  # the reads after the writes now differ
    assert "--writes" not in done.stderr


def test_writes_are_sent_with_writes(sim_logs: dict[str, Path]) -> None:
    with fresh_sim() as sim:
        done = simlog.replay(str(sim_logs["writes"]), "--to", f"127.0.0.1:{sim.port}", "--writes")
        written = [_sim_holding(sim, a) for a in (201, 202, 203, 300)]
        coils = sim.call(lambda robot, _now: robot.coils[3:7])
    assert written == [1, 2, 3, 42]
    assert coils == [1, 1, 0, 1]
    assert done.returncode == 0, done.stdout + done.stderr
    assert "re-sent 10 recorded requests" in done.stdout
    assert "not sent" not in done.stdout
    assert "warning: --writes: the recorded writes are sent to" in done.stderr


def test_speed_paces_the_requests_like_the_original(sim_logs: dict[str, Path]) -> None:
    with McapLog(sim_logs["reads"]) as log:
        exchanges = list(recorded_exchanges(log))
    span = exchanges[-1].ts - exchanges[0].ts
    assert span > 0
    image = RegisterImage.from_exchanges(exchanges)
    speed = span / 0.5  # the whole log in about half a second
    with EmulatorServer(image) as srv:
        client = LiveClient(srv.host, srv.port)
        try:
            t0 = time.monotonic()
            report = resend(exchanges, client, speed=speed)
            took = time.monotonic() - t0
            t0 = time.monotonic()
            resend(exchanges, client)
            fast = time.monotonic() - t0
        finally:
            client.close()
    assert report.same == 10 and report.different == 0
    assert took >= 0.45, took
    assert fast < took


@contextmanager
def silent_server() -> Iterator[int]:
    """A TCP server that reads every request and never answers."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    stop = threading.Event()

    def run() -> None:
        listener.settimeout(0.1)
        conns = []
        while not stop.is_set():
            try:
                conn, _ = listener.accept()
                conn.setblocking(False)
                conns.append(conn)
            except TimeoutError:
                pass
            for conn in conns:
                try:
                    conn.recv(4096)
                except (BlockingIOError, OSError):
                    pass
        for conn in conns:
            conn.close()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield port
    finally:
        stop.set()
        thread.join(5)
        listener.close()


def test_a_silent_server_is_reported_per_request(sim_logs: dict[str, Path]) -> None:
    with silent_server() as port:
        done = simlog.replay(
            str(sim_logs["reads"]), "--to", f"127.0.0.1:{port}", "--answer-timeout", "0.1"
        )
    assert done.returncode == 3, done.stderr
    assert "recorded values, live no answer" in done.stdout
    assert "0 answered as recorded, 10 differently (10 not answered live)" in done.stdout


def test_unreachable_server_is_an_error(sim_logs: dict[str, Path]) -> None:
    with socket.create_server(("127.0.0.1", 0)) as s:
        port = s.getsockname()[1]  # closed again below: nothing listens there
    done = simlog.replay(str(sim_logs["reads"]), "--to", f"127.0.0.1:{port}")
    assert done.returncode == 1
    assert f"cannot connect to 127.0.0.1:{port}" in done.stderr
    assert "Traceback" not in done.stderr
    with pytest.raises(LiveError):
        LiveClient("127.0.0.1", port, 1.0)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--writes"], "--writes needs --serve or --to"),
        (["--answer-timeout", "1"], "--answer-timeout needs --serve or --to"),
        (
            ["--to", "127.0.0.1:1502", "--miss-exception", "4"],
            "--miss-exception applies to --serve",
        ),
        (["--to", "127.0.0.1:1502", "--grep", "x"], "--grep does not apply to --to"),
        (["--to", "127.0.0.1"], "--to"),
        (["--to", "127.0.0.1:0"], "port out of range"),
        (["--serve", "127.0.0.1:0", "--writes"], "--writes applies to --to"),
    ],
)
def test_to_usage_errors(sim_logs: dict[str, Path], args: list[str], message: str) -> None:
    done = simlog.replay(str(sim_logs["reads"]), *args)
    assert done.returncode == 2, done.stdout + done.stderr
    assert message in done.stderr
    assert "Traceback" not in done.stderr


def test_filters_select_the_requests(sim_logs: dict[str, Path]) -> None:
    with fresh_sim() as sim:
        done = simlog.replay(
            str(sim_logs["reads"]), "--to", f"127.0.0.1:{sim.port}", "--fc", "4", "--unit", "1"
        )
    assert done.returncode == 0, done.stderr
    assert "re-sent 3 recorded requests" in done.stdout


def test_sigterm_ends_a_paced_resend_with_the_summary(sim_logs: dict[str, Path]) -> None:
    import signal
    import subprocess
    import sys

    from mbmon.sim.server import SimServer

    answered = threading.Event()
    with SimServer(on_packet=lambda sending, _data: sending and answered.set()) as sim:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mbmon", "replay", str(sim_logs["reads"]),
             "--to", f"127.0.0.1:{sim.port}", "--speed", "0.0001"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=simlog.ENV,
        )  # fmt: skip
        assert answered.wait(60), "the first request never came"
        time.sleep(0.5)  # its answer read; the second request is hours away
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 128 + signal.SIGTERM, err  # as every command a signal ends
    assert "re-sent 1 recorded requests" in out
    assert "Traceback" not in err


@pytest.mark.parametrize("module", ["mbmon.io.exchanges", "mbmon.io.emulate", "mbmon.io.resend"])
def test_replay_server_modules_import_neither_the_cli_nor_pymodbus(module: str) -> None:
    """Dependencies point down: the io modules never pull in the command line, and the
    emulator is mbmon's own server (pymodbus serves only the simulator)."""
    import subprocess
    import sys

    code = (
        f"import sys, {module}; "
        "bad = [m for m in ('mbmon.cli', 'mbmon.commands', 'pymodbus', "
        "'scapy', 'serial') if m in sys.modules]; print(','.join(bad))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, env=simlog.ENV
    )
    assert out.stdout.strip() == "", f"{module} imports {out.stdout.strip()}"
