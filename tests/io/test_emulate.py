"""``replay --serve``: the register image (byte tables) and the emulated server against
logs recorded from ``mbmon sim`` through ``mbmon proxy -w`` (real sockets, real MCAP)."""

from __future__ import annotations

import signal
import socket
import struct
from pathlib import Path
from typing import Any

import pytest
import simlog
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.io.emulate import EmulatorServer, RegisterImage, ranges
from mbmon.io.exchanges import Exchange, recorded_exchanges
from mbmon.io.mcap.reader import McapLog
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import decode_pdu

ROOT = Path(__file__).resolve().parents[2]

# --------------------------------------------------------------------------- the image


def ex(req: str, resp: str | None, unit: int = 1) -> Exchange:
    request = decode_pdu(bytes.fromhex(req), response=False)
    response = None
    if resp is not None:
        response = decode_pdu(bytes.fromhex(resp), response=True, request=request)
    return Exchange(0, 0.0, None, unit, request, response)


def ask(image: RegisterImage, req: str, unit: int = 1) -> str:
    return image.answer(unit, decode_pdu(bytes.fromhex(req), response=False)).hex()


def test_reads_learn_values_per_unit_and_table() -> None:
    image = RegisterImage.from_exchanges(
        [
            ex("0300640002", "030400640005"),  # HR100..101 = 100, 5
            ex("0400640001", "04020007"),  # IR100 = 7: another table
            ex("0100000003", "010105"),  # coils 0..2 = 1 0 1 (padding bits dropped)
            ex("0300640001", "03020009", unit=2),
        ]
    )
    assert ask(image, "0300640002") == "030400640005"
    assert ask(image, "0300650001") == "03020005"  # a part of what was read
    assert ask(image, "0400640001") == "04020007"
    assert ask(image, "0100000003") == "010105"
    assert ask(image, "0100010002") == "010102"  # coils 1..2 = 0 1
    assert ask(image, "0300640001", unit=2) == "03020009"
    assert image.units == [1, 2]
    assert image.misses == {}


def test_first_and_last_state() -> None:
    log = [ex("0300640001", "03020001"), ex("0300640001", "03020002")]
    assert ask(RegisterImage.from_exchanges(log), "0300640001") == "03020001"
    assert ask(RegisterImage.from_exchanges(log, state="last"), "0300640001") == "03020002"
    with pytest.raises(ValueError):
        RegisterImage.from_exchanges(log, state="middle")


def test_follow_gives_a_repeated_read_its_recorded_answers_in_order() -> None:
    # IR524 polled: Running, Running, Idle; IR300..301 read once; a refusal in between
    log = [
        ex("04020c0001", "04020002"),
        ex("04012c0002", "0404000a0000"),
        ex("04020c0001", "04020002"),
        ex("03079d0001", "8302"),
        ex("04020c0001", "04020001"),
        ex("03079d0001", "03020005"),
    ]
    image = RegisterImage.from_exchanges(log, state="follow")
    assert [ask(image, "04020c0001") for _ in range(5)] == ["04020002"] * 2 + ["04020001"] * 3
    assert ask(image, "03079d0001") == "8302"  # the recorded answers, refusals too
    assert ask(image, "03079d0001") == "03020005"
    assert ask(image, "03079d0001") == "03020005"
    assert ask(image, "04012c0001") == "0402000a"  # not recorded as such: from the image
    assert image.misses == {} and image.answered == 9
    # the same log as a fixed image: IR524 stays Running for ever
    first = RegisterImage.from_exchanges(log)
    assert {ask(first, "04020c0001") for _ in range(5)} == {"04020002"}


def test_follow_keeps_what_the_new_client_wrote() -> None:
    log = [
        ex("0300c80002", "030400000000"),  # R200..R201 = 0, 0
        ex("1000c800020400010064", "1000c80002"),  # the recorded client wrote 1, 100
        ex("0300c80002", "030400010064"),
        ex("0300c80002", "030400010064"),
    ]
    image = RegisterImage.from_exchanges(log, state="follow")
    assert ask(image, "0300c80002") == "030400000000"
    assert ask(image, "0600c90007") == "0600c90007"  # this client writes R201 = 7
    assert ask(image, "0300c80002") == "030400010007"  # R200 as recorded, R201 its own
    assert ask(image, "0300c80001") == "03020001"  # the image moved on with the recording


def test_recorded_writes_make_addresses_known() -> None:
    image = RegisterImage.from_exchanges(
        [
            ex("06012c002a", "06012c002a"),  # HR300 = 42
            ex("1000c900020400010002", "1000c90002"),  # HR201..202 = 1, 2
            ex("0f000400030105", "0f00040003"),  # coils 4..6 = 1 0 1
            ex("050003ff00", "050003ff00"),  # coil 3 = 1
            ex("0601f40001", "8602"),  # refused: HR500 stays unknown
            ex("0601f50001", None),  # never answered: HR501 stays unknown
        ]
    )
    assert ask(image, "03012c0001") == "0302002a"
    assert ask(image, "0300c90002") == "030400010002"
    assert ask(image, "0100030004") == "01010b"  # coils 3..6 = 1 1 0 1
    assert ask(image, "0301f40001") == "8302"
    assert ask(image, "0301f50001") == "8302"
    assert sorted(m.address for m in image.misses.values()) == [500, 501]


def test_client_writes_change_the_image_and_unknown_writes_miss() -> None:
    image = RegisterImage.from_exchanges(
        [ex("0300640003", "0306000100020003"), ex("0100000008", "0101ff")]
    )
    assert ask(image, "0600650009") == "0600650009"  # echo
    assert ask(image, "1000640002040007000a") == "1000640002"
    assert ask(image, "0300640003") == "03060007000a0003"
    assert ask(image, "0500020000") == "0500020000"
    assert ask(image, "0f000500020100") == "0f00050002"
    assert ask(image, "0100000008") == "01019b"  # coils 2, 5 and 6 cleared
    assert ask(image, "0600c80001") == "8602"  # HR200 never seen: not written
    assert ask(image, "0300c80001") == "8302"
    assert ask(image, "10006600020400010002") == "9002"  # HR103 unknown
    assert ask(image, "0300640003") == "03060007000a0003"  # the refused write changed nothing


def test_mask_write_and_read_write_multiple() -> None:
    image = RegisterImage.from_exchanges(
        [
            ex("03000a0002", "030400f0000f"),  # HR10 = 0x00F0, HR11 = 0x000F
            ex("16000a00f00025", "16000a00f00025"),  # (0xF0 & 0xF0) | (0x25 & ~0xF0) = 0xF5
        ],
        state="last",  # the write after the read counts
    )
    assert ask(image, "03000a0001") == "030200f5"
    assert ask(image, "16000b00ff0100") == "16000b00ff0100"  # (0x0F & 0xFF) | 0x0100
    assert ask(image, "03000b0001") == "0302010f"
    # 17: write HR11 = 7 first, then read HR10..11
    assert ask(image, "17000a0002000b0001020007") == "170400f50007"
    assert ask(image, "16006300ff0000") == "9602"  # HR99 never seen


def test_recorded_exceptions_are_answered_as_recorded() -> None:
    image = RegisterImage.from_exchanges(
        [
            ex("0300640001", "8306"),  # busy once ...
            ex("0300640001", "03020001"),  # ... then answered: the values win
            ex("03079d0005", "8302"),
            ex("0300640001", "830b", unit=2),  # a gateway's answer for unit 2
            ex("0600640000", "8603"),  # a refused value; another value would be a miss
            ex("11", "9101"),
        ]
    )
    assert ask(image, "0300640001") == "03020001"
    assert ask(image, "03079d0005") == "8302"
    assert ask(image, "0300640001", unit=2) == "830b"
    assert ask(image, "0600640000") == "8603"
    assert ask(image, "11") == "9101"
    assert image.misses == {}


def test_other_function_codes_verbatim_and_misses_listed() -> None:
    image = RegisterImage.from_exchanges(
        [ex("11", "11050102030400ff"), ex("0800000102", "0800000102")], miss_exception=4
    )
    assert ask(image, "11") == "11050102030400ff"
    assert ask(image, "0800000102") == "0800000102"
    assert ask(image, "0800000103") == "8804"  # never this request
    assert ask(image, "11", unit=3) == "9104"
    assert ask(image, "0300000003") == "8304"
    assert ask(image, "0300000003") == "8304"
    report = image.miss_report()
    assert "unit 1, 03 Read Holding Registers, holding registers 0-2: 2 times" in report
    assert "unit 1, 08 Diagnostics (this request never seen): once" in report
    assert "unit 3, 11 Report Server ID (this request never seen): once" in report


def test_partly_known_reads_name_the_unknown_addresses() -> None:
    image = RegisterImage.from_exchanges([ex("0300640002", "030400010002")])
    assert ask(image, "0300630005") == "8302"
    assert image.miss_report() == [
        "unit 1, 03 Read Holding Registers, holding registers 99-103 "
        "(never seen: 99, 102-103): once"
    ]


def test_malformed_request_is_illegal_value() -> None:
    image = RegisterImage.from_exchanges([ex("0300640001", "03020001")])
    assert ask(image, "0300640000") == "8303"  # count 0
    assert image.misses == {}


@settings(max_examples=300, deadline=None)
@given(
    pdu=st.binary(min_size=1, max_size=40),
    fc=st.sampled_from([1, 2, 3, 4, 5, 6, 15, 16, 22, 23, 8, 17, 0x2B, 0x41, 0x81]),
    unit=st.integers(0, 255),
)
def test_any_request_gets_an_answer_never_a_traceback(pdu: bytes, fc: int, unit: int) -> None:
    image = RegisterImage.from_exchanges(
        [ex("0300000010", "0320" + "0001" * 16), ex("0100000010", "0102ffff")]
    )
    request = decode_pdu(bytes([fc]) + pdu, response=False)
    answer = image.answer(unit, request)
    assert answer and answer[0] & 0x7F == fc & 0x7F
    assert len(answer) <= 253


def test_miss_list_is_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    import mbmon.io.emulate as emulate

    monkeypatch.setattr(emulate, "MAX_MISS_KINDS", 3)
    image = RegisterImage()
    for address in range(10):
        assert ask(image, f"03{address:04x}0001") == "8302"
    assert ask(image, "0300000001") == "8302"
    assert len(image.misses) == 3 and image.missed == 11
    assert image.miss_report()[-1] == "7 more requests of other kinds"


def test_ranges() -> None:
    assert ranges([7, 1, 2, 3, 3]) == ((1, 3), (7, 7))
    assert ranges([]) == ()


# --------------------------------------------------------------------------- logs from sim


@pytest.fixture(scope="module")
def sim_logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, list[Any]]]:
    """``reads`` and ``writes``: a log each, recorded from a fresh sim, and what the client got."""
    from mbmon.sim.server import SimServer

    tmp = tmp_path_factory.mktemp("simlogs")
    out: dict[str, tuple[Path, list[Any]]] = {}
    for name, traffic in (("reads", simlog.reads), ("writes", simlog.writes_then_reads)):
        with SimServer() as sim:
            log = tmp / f"{name}.mcap"
            out[name] = (log, simlog.record(sim.port, log, traffic))
    return out


def _exchanges(log: Path) -> list[Exchange]:
    with McapLog(log) as mcap:
        return list(recorded_exchanges(mcap))


def _send(sock: socket.socket, tid: int, unit: int, pdu: bytes) -> bytes:
    sock.sendall(encode_adu(tid, unit, pdu))
    head = b""
    while len(head) < 7:
        head += sock.recv(7 - len(head))
    got_tid, _pid, length, got_unit = struct.unpack(">HHHB", head)
    assert (got_tid, got_unit) == (tid, unit)
    body = b""
    while len(body) < length - 1:
        body += sock.recv(length - 1 - len(body))
    return body


@pytest.mark.parametrize("name", ["reads", "writes"])
def test_serve_answers_a_pymodbus_client_as_the_recorded_server(
    sim_logs: dict[str, tuple[Path, list[Any]]], name: str
) -> None:
    log, recorded = sim_logs[name]
    traffic = simlog.reads if name == "reads" else simlog.writes_then_reads
    with simlog.served(log) as srv:
        again = simlog.run_traffic(srv.port, traffic)
        code, err = srv.stop()
    assert again == recorded
    assert code == 0, err
    assert ", 0 not (exception 02)" in err
    assert "could not answer" not in err


@pytest.mark.parametrize("name", ["reads", "writes"])
def test_serve_answers_every_recorded_request_pdu_identically(
    sim_logs: dict[str, tuple[Path, list[Any]]], name: str
) -> None:
    log, _ = sim_logs[name]
    exchanges = _exchanges(log)
    assert len(exchanges) >= 10
    with McapLog(log) as mcap:
        image = RegisterImage.from_exchanges(recorded_exchanges(mcap))
    with EmulatorServer(image) as srv, socket.create_connection((srv.host, srv.port), 5) as s:
        for tid, x in enumerate(exchanges, 1):
            assert x.response is not None
            assert _send(s, tid, x.unit, x.request.raw) == x.response.raw, x
    assert image.misses == {}


def test_serve_answers_the_5452_program_as_the_recorded_robot(tmp_path: Path) -> None:
    """The recorded program again, against its own log: every answer as recorded,
    IR524 Running then Idle included, so it ends at A1 = 90 as it did on the sim."""
    from mbmon.sim.server import SimServer

    log = tmp_path / "program.mcap"
    with SimServer() as sim:
        recorded = simlog.record(sim.port, log, simlog.program)
    polls = [r for f, a, _v, r in recorded if (f, a) == (4, 524)]
    assert polls.count((2,)) >= 2 and polls[-1] == (1,)  # the robot moved, in time
    with simlog.served(log) as srv:
        again = simlog.run_traffic(srv.port, simlog.program)
        code, err = srv.stop()
    assert again == recorded
    assert code == 0, err
    assert ", 0 not (exception 02)" in err
    # a fixed image cannot: IR524 stays Running and the program gives up
    from mbmon.sim.program import ProgramError, run_program

    with simlog.served(log, "--state", "first") as srv:
        with pytest.raises(ProgramError, match="still Running"):
            run_program("127.0.0.1", srv.port, poll=0.01, timeout=0.5)
        srv.stop()


def test_serve_misses_get_exception_02_and_are_listed(
    sim_logs: dict[str, tuple[Path, list[Any]]],
) -> None:
    log, _ = sim_logs["reads"]
    with simlog.served(log) as srv:
        c = simlog.client(srv.port)
        try:
            assert simlog.result(c.read_holding_registers(500, count=3)) == ("exc", 2)
            assert simlog.result(c.read_holding_registers(500, count=3)) == ("exc", 2)
            assert simlog.result(c.read_holding_registers(209, count=3)) == ("exc", 2)
            assert simlog.result(c.write_register(900, 1)) == ("exc", 2)
            assert simlog.result(c.read_coils(0, count=4, device_id=7)) == ("exc", 2)
            assert simlog.result(c.read_holding_registers(100, count=1)) == ("regs", [100])
        finally:
            c.close()
        code, err = srv.stop(signal.SIGTERM)
    assert code == 0
    assert "5 not (exception 02)" in err
    assert "  unit 1, 03 Read Holding Registers, holding registers 500-502: 2 times" in err
    assert "holding registers 209-211 (never seen: 211): once" in err
    assert "  unit 1, 06 Write Single Register, holding registers 900: once" in err
    assert "  unit 7, 01 Read Coils, coils 0-3: once" in err
    assert "Traceback" not in err


def test_serve_miss_exception_option(sim_logs: dict[str, tuple[Path, list[Any]]]) -> None:
    log, _ = sim_logs["reads"]
    with simlog.served(log, "--miss-exception", "4") as srv:
        c = simlog.client(srv.port)
        try:
            assert simlog.result(c.read_input_registers(400, count=2)) == ("exc", 4)
        finally:
            c.close()
        code, err = srv.stop()
    assert code == 0
    assert "1 not (exception 04)" in err


def test_serve_client_writes_update_the_image_across_connections(
    sim_logs: dict[str, tuple[Path, list[Any]]],
) -> None:
    log, _ = sim_logs["reads"]
    with simlog.served(log) as srv:
        c = simlog.client(srv.port)
        try:
            assert simlog.result(c.write_register(201, 77)) == ("regs", [77])
            assert simlog.result(c.write_coil(3, True)) == ("bits", [True])
        finally:
            c.close()
        c = simlog.client(srv.port)
        try:
            regs = simlog.result(c.read_holding_registers(201, count=2))
            bits = simlog.result(c.read_coils(0, count=8))
        finally:
            c.close()
        code, err = srv.stop()
    assert regs == ("regs", [77, 0])
    assert bits == ("bits", [False, False, False, True, False, False, False, False])
    assert code == 0
    assert "2 client connection(s)" in err


def test_serve_state_last(sim_logs: dict[str, tuple[Path, list[Any]]]) -> None:
    log, _ = sim_logs["writes"]
    with simlog.served(log, "--state", "last") as srv:
        c = simlog.client(srv.port)
        try:
            last = simlog.result(c.read_holding_registers(300, count=1))
        finally:
            c.close()
        srv.stop()
    with simlog.served(log) as srv:
        c = simlog.client(srv.port)
        try:
            first = simlog.result(c.read_holding_registers(300, count=1))
        finally:
            c.close()
        srv.stop()
    assert (first, last) == (("regs", [0]), ("regs", [42]))


# --------------------------------------------------------------------------- RTU logs


def _read_capture(capture: Path, out: Path) -> Path:
    done = simlog.subprocess.run(
        [simlog.sys.executable, "-m", "mbmon", "read", str(capture), "-q", "-w", str(out)],
        capture_output=True, text=True, env=simlog.ENV, timeout=60,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return out


def test_rtu_log_gives_the_exchanges_of_the_same_session_over_tcp(tmp_path: Path) -> None:
    rtu_capture = ROOT / "captures" / "hrss_rtu.pcap"
    tcp_capture = ROOT / "captures" / "hrss_ptp.pcap"
    if not rtu_capture.exists() or not tcp_capture.exists():
        pytest.skip("captures/hrss_rtu.pcap or hrss_ptp.pcap absent")
    rtu = _exchanges(_read_capture(rtu_capture, tmp_path / "rtu.mcap"))
    tcp = _exchanges(_read_capture(tcp_capture, tmp_path / "tcp.mcap"))

    def key(x: Exchange) -> tuple[int, bytes, bytes | None]:
        return x.unit, x.request.raw, x.response.raw if x.response else None

    assert len(rtu) == 28
    assert [key(x) for x in rtu] == [key(x) for x in tcp]
    # served over TCP with the bus's unit id: every recorded request is answered
    # (IR524, the motion state, polled Running ... Idle: first Running, last Idle)
    first = RegisterImage.from_exchanges(rtu)
    last = RegisterImage.from_exchanges(rtu, state="last")
    for image in (first, last):
        with EmulatorServer(image) as srv, socket.create_connection((srv.host, srv.port)) as s:
            for tid, x in enumerate(rtu, 1):
                answer = _send(s, tid, x.unit, x.request.raw)
                assert x.response is not None
                assert answer[0] == x.response.raw[0], x  # same function code, or exception
                assert len(answer) == len(x.response.raw)
        assert image.misses == {}
    ask_ir524 = decode_pdu(bytes.fromhex("04020c0001"), response=False)
    assert first.answer(1, ask_ir524).hex() == "04020002"
    assert last.answer(1, ask_ir524).hex() == "04020001"
    assert first.units == [1]


# --------------------------------------------------------------------------- usage


@pytest.mark.parametrize(
    "args, message",
    [
        (["--serve", "--to", "127.0.0.1:1"], "exclude each other"),
        (["--serve", "127.0.0.1:0", "--speed", "2"], "--speed applies to --to"),
        (["--serve", "127.0.0.1:0", "--json"], "--json does not apply to --serve"),
        (["--serve", "nohost"], "--serve 'nohost': not a port number"),
        (["--serve", "127.0.0.1:70000"], "port out of range 0..65535"),
        (["--miss-exception", "3"], "--miss-exception needs --serve or --to"),
        (["--state", "last"], "--state needs --serve or --to"),
    ],
)
def test_serve_usage_errors(
    sim_logs: dict[str, tuple[Path, list[Any]]], args: list[str], message: str
) -> None:
    log, _ = sim_logs["reads"]
    done = simlog.replay(str(log), *args)
    assert done.returncode == 2, done.stderr
    assert message in done.stderr
    assert "Traceback" not in done.stderr


def test_serve_unreadable_log(tmp_path: Path) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not mcap at all")
    done = simlog.replay(str(bad), "--serve", "127.0.0.1:0")
    assert done.returncode == 1
    assert "not an MCAP file" in done.stderr
