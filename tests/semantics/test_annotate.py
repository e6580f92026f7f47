"""Annotator notes from real PDUs (encoded, then decoded) against the HRSS and XEG profiles.

Values come from the manual: Appendix II (A1 = 90.830°, X = -399.958 mm),
Tables 44-50 (coils, PTP, Set PR), Table 14 (IR524, error codes), Table 56 (XEG).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import pytest

from mbmon.model import (
    Annotation,
    Direction,
    Frame,
    Stream,
    Transaction,
    Transport,
    TxStatus,
)
from mbmon.protocol.pdu import (
    decode_pdu,
    encode_exception,
    encode_read_request,
    encode_read_response,
    encode_write_multiple_request,
    encode_write_multiple_response,
    encode_write_single,
)
from mbmon.semantics.annotate import Annotator
from mbmon.semantics.profile import ProfileBinding, builtin_profile_text
from mbmon.semantics.words import split_i32, u16

ROBOT = Stream(0, Transport.TCP, "192.168.0.10:50123", "192.168.0.2:502")
GRIPPER = Stream(1, Transport.RTU, "/dev/ttyUSB0", "/dev/ttyUSB0")


def frame(raw: bytes, response: bool, stream: Stream, unit: int, req: Frame | None = None) -> Frame:
    pdu = decode_pdu(raw, response, req.pdu if req is not None else None)
    assert pdu.malformed is None, pdu.malformed
    direction = Direction.S2C if response else Direction.C2S
    return Frame(1.0, stream, direction, unit, 7, pdu, raw)


def pending(raw: bytes, stream: Stream = ROBOT, unit: int = 1) -> Transaction:
    return Transaction(1.0, TxStatus.PENDING, frame(raw, False, stream, unit), None)


def answered(req_raw: bytes, resp_raw: bytes, stream: Stream = ROBOT, unit: int = 1) -> Transaction:
    req = frame(req_raw, False, stream, unit)
    resp = frame(resp_raw, True, stream, unit, req)
    status = TxStatus.EXCEPTION if resp_raw[0] & 0x80 else TxStatus.ANSWERED
    return Transaction(1.01, status, req, resp, 0.01)


def read(fc: int, address: int, values: Sequence[int], stream: Stream = ROBOT, unit: int = 1):
    return answered(
        encode_read_request(fc, address, len(values)),
        encode_read_response(fc, [u16(v) for v in values]),
        stream,
        unit,
    )


def i32_words(*values: int) -> list[int]:
    return [u16(w) for v in values for w in split_i32(v)]


@pytest.fixture
def xeg_only() -> Annotator:
    """The XEG profile everywhere: no HRSS session, so only profile notes."""
    return Annotator(ProfileBinding.parse(["xeg"]))


@pytest.fixture(scope="module")
def nosession_profile(tmp_path_factory: pytest.TempPathFactory) -> str:
    """The HRSS map as a user profile file without ``session``: profile notes only."""
    text = builtin_profile_text("hrss")
    assert 'session = "hrss"\n' in text
    path = tmp_path_factory.mktemp("profiles") / "hrss-nosession.toml"
    path.write_text(text.replace('session = "hrss"\n', ""), "utf-8")
    return str(path)


@pytest.fixture
def hrss_notes(nosession_profile: str) -> Annotator:
    a = Annotator(ProfileBinding.parse([nosession_profile]))
    profile = a.binding.profiles()[0]
    assert profile.session is None and profile.name == "hrss"
    return a


def notes(a: Annotator, tx: Transaction) -> list[str]:
    return list(a.annotate(tx).notes)


# ---------------------------------------------------------------------- bits


def test_coil_write_si1_start(hrss_notes: Annotator) -> None:
    assert notes(hrss_notes, pending(encode_write_single(0x05, 0, True))) == ["SI1 Start = ON"]
    assert notes(hrss_notes, pending(encode_write_single(0x05, 2, False))) == ["SI3 Stop = OFF"]


def test_coil_write_do3(hrss_notes: Annotator) -> None:
    assert notes(hrss_notes, pending(encode_write_single(0x05, 302, False))) == ["DO[3] = OFF"]
    # the echo answers with the same note
    tx = answered(encode_write_single(0x05, 302, True), encode_write_single(0x05, 302, True))
    assert notes(hrss_notes, tx) == ["DO[3] = ON"]


def test_write_multiple_coils_do1_to_do5(hrss_notes: Annotator) -> None:
    # §5.4.5.2 line 21: MBC_WRITE_COIL(1,300,WRITE_DATA,5) with 1,1,0,0,1
    req = encode_write_multiple_request(0x0F, 300, [1, 1, 0, 0, 1])
    assert notes(hrss_notes, pending(req)) == ["DO[1..5] = ON ON OFF OFF ON"]
    tx = answered(req, encode_write_multiple_response(0x0F, 300, 5))
    assert notes(hrss_notes, tx) == ["DO[1..5] written"]


def test_read_discrete_inputs_so_and_di(hrss_notes: Annotator) -> None:
    tx = read(0x02, 0, [1, 0, 0, 1, 0, 0, 0, 0, 0, 1])
    assert notes(hrss_notes, tx) == [
        "SO1 Run = ON",
        "SO2 Held = OFF",
        "SO3 Fault = OFF",
        "SO4 Ready = ON",
        "SO5 ACK1 = OFF",
        "SO6 ACK2 = OFF",
        "SO7 ACK3 = OFF",
        "SO8 ACK4 = OFF",
        "SO9..SO10 = OFF ON",
    ]
    # §5.4.5.2 line 8: MBC_READ_DINPUT(1,300,READ_DATA,8) reads DI[1]..DI[8]
    assert notes(hrss_notes, pending(encode_read_request(0x02, 300, 8))) == ["read DI[1..8]"]
    tx = read(0x02, 300, [0, 1, 0, 0, 0, 0, 0, 1])
    assert notes(hrss_notes, tx) == ["DI[1..8] = OFF ON OFF OFF OFF OFF OFF ON"]


def test_long_bit_run_lists_the_on_ones(hrss_notes: Annotator) -> None:
    bits = [0] * 248
    bits[3] = bits[100] = 1
    tx = read(0x01, 8, bits)
    assert notes(hrss_notes, tx) == ["SI9..SI256 = 2 ON (SI12, SI109)"]
    assert notes(hrss_notes, read(0x01, 300, [0] * 20)) == ["DO[1..20] = all OFF"]


# ---------------------------------------------------------------------- registers


def test_fc10_ptp_parameters(hrss_notes: Annotator) -> None:
    # Table 46: R201 = 0 (PTP), R202 = 0 (joint), R203/R204 = A1 90° = 24464, 1
    tx = pending(encode_write_multiple_request(0x10, 201, [0, 0, 24464, 1]))
    assert notes(hrss_notes, tx) == ["R201 = PTP (0)", "R202..R204 parameters = 0 24464 1"]


def test_fc06_execute(hrss_notes: Annotator) -> None:
    assert notes(hrss_notes, pending(encode_write_single(0x06, 200, 1))) == ["R200 = 1 (execute)"]
    assert notes(hrss_notes, pending(encode_write_single(0x06, 200, 0))) == ["R200 = 0 (ready)"]
    assert notes(hrss_notes, pending(encode_write_single(0x06, 201, 100))) == [
        "R201 = Set PR (100)"
    ]
    assert notes(hrss_notes, pending(encode_write_single(0x06, 201, 7))) == ["R201 = 7 (unknown)"]


def test_read_joint_angles_appendix_ii(hrss_notes: Annotator) -> None:
    # Appendix II: (25294, 1) -> 90.830 degrees; (-6742, -7) -> -399.958
    words = [25294, 1, *i32_words(0, -90000), -6742, -7, *i32_words(180000, 1)]
    tx = read(0x04, 300, words)
    assert notes(hrss_notes, tx) == [
        "A1 = 90.830°",
        "A2 = 0.000°",
        "A3 = -90.000°",
        "A4 = -399.958°",
        "A5 = 180.000°",
        "A6 = 0.001°",
    ]
    assert notes(hrss_notes, pending(encode_read_request(0x04, 300, 12))) == ["read A1..A6"]


def test_read_cartesian_appendix_ii(hrss_notes: Annotator) -> None:
    words = [-6742, -7, *i32_words(300000, -300000, 180000, 0, 90000)]
    assert notes(hrss_notes, read(0x04, 400, words)) == [
        "X = -399.958 mm",
        "Y = 300.000 mm",
        "Z = -300.000 mm",
        "A = 180.000°",
        "B = 0.000°",
        "C = 90.000°",
    ]


def test_split_32_bit_halves_are_marked(hrss_notes: Annotator) -> None:
    # IR301..IR304: A1's high word, all of A2, A3's low word
    tx = read(0x04, 301, [1, *i32_words(45000), 25294])
    assert notes(hrss_notes, tx) == [
        "A1 (high word) = 1 (low word not in this read)",
        "A2 = 45.000°",
        "A3 (low word) = 25294 (high word not in this read)",
    ]
    # a write of one half of a timer
    tx = pending(encode_write_single(0x06, 304, u16(-27680)))
    assert notes(hrss_notes, tx) == ["Timer[3] (low word) = -27680 (high word not in this write)"]


def test_timer_and_counter(hrss_notes: Annotator) -> None:
    # Timer[n] at 298+2n: Timer[3] = R304/R305; 1.250 s = 1250 ms
    tx = pending(encode_write_multiple_request(0x10, 304, i32_words(1250)))
    assert notes(hrss_notes, tx) == ["Timer[3] = 1.250 s"]
    tx = pending(encode_write_multiple_request(0x10, 400, i32_words(-300000, 7)))
    assert notes(hrss_notes, tx) == ["Counter[1] = -300000", "Counter[2] = 7"]


def test_pr_block_set_pr_example_7(hrss_notes: Annotator) -> None:
    # PR[2] block at 1000 + 19 = 1019: type 2 (Cartesian), X = 90 mm (Table 50 values)
    words = [2, *i32_words(90000, 0, 0, 0, 0, 0)]
    tx = pending(encode_write_multiple_request(0x10, 1019, words))
    assert notes(hrss_notes, tx) == [
        "PR[2].type = Cartesian (2)",
        "PR[2].X = 90.000 mm",
        "PR[2].Y = 0.000 mm",
        "PR[2].Z = 0.000 mm",
        "PR[2].A = 0.000°",
        "PR[2].B = 0.000°",
        "PR[2].C = 0.000°",
    ]
    # a later write of Value1 alone uses the type last seen on this server and unit
    tx = pending(encode_write_multiple_request(0x10, 1020, i32_words(12345)))
    assert notes(hrss_notes, tx) == ["PR[2].X = 12.345 mm"]


def test_pr_block_type_unknown_or_joint(hrss_notes: Annotator) -> None:
    tx = pending(encode_write_multiple_request(0x10, 1039, i32_words(90000)))  # PR[3].Value1
    assert notes(hrss_notes, tx) == ["PR[3].Value1 = 90.000"]
    tx = read(0x03, 1038, [1, *i32_words(90000)])  # PR[3] joint
    assert notes(hrss_notes, tx) == ["PR[3].type = Joint (1)", "PR[3].A1 = 90.000°"]
    # the memory is per server: another robot does not know PR[3]'s type
    other = Stream(2, Transport.TCP, "192.168.0.10:50124", "192.168.0.3:502")
    tx = pending(encode_write_multiple_request(0x10, 1039, i32_words(90000)), stream=other)
    assert notes(hrss_notes, tx) == ["PR[3].Value1 = 90.000"]


def test_motion_state_and_status(hrss_notes: Annotator) -> None:
    assert notes(hrss_notes, read(0x04, 524, [2])) == ["IR524 motion state = Running (2)"]
    assert notes(hrss_notes, read(0x04, 524, [1])) == ["IR524 motion state = Idle (1)"]
    assert notes(hrss_notes, pending(encode_read_request(0x04, 524, 1))) == [
        "read IR524 motion state"
    ]
    assert notes(hrss_notes, read(0x04, 200, [1, 0])) == [
        "IR200 command status = Success (1)",
        "IR201 current action = PTP (0)",
    ]


def test_robot_state_block_520_524(hrss_notes: Annotator) -> None:
    tx = read(0x04, 520, [*i32_words(1500250), 1, 200, 4])
    assert notes(hrss_notes, tx) == [
        "IR520 TCP speed = 1500.250 mm/s",
        "IR522 excitation = Excited (1)",
        "IR523 acceleration time = 0.200 s",
        "IR524 motion state = Delay (4)",
    ]


def test_error_codes_in_hex(hrss_notes: Annotator) -> None:
    # IR500 low word = error number 2, IR501 high word = error number 1
    tx = read(0x04, 500, [0x002A, 0x1008, 0, 0xC001])
    assert notes(hrss_notes, tx) == [
        "IR500 drive error = 0x1008002A",
        "IR502 HRSS error = 0xC0010000",
    ]
    tx = read(0x04, 501, [0x1008])
    assert notes(hrss_notes, tx) == [
        "IR500 drive error (high word) = 0x1008 (low word not in this read)"
    ]


def test_speed_out_of_range_is_marked(hrss_notes: Annotator) -> None:
    # §5.4.5.2: WRITE_DATA[1] = 90 to R100
    assert notes(hrss_notes, pending(encode_write_single(0x06, 100, 90))) == [
        "R100 set speed = 90%"
    ]
    assert notes(hrss_notes, pending(encode_write_single(0x06, 100, 150))) == [
        "R100 set speed = 150% (out of range 1..100)"
    ]
    assert notes(hrss_notes, read(0x04, 100, [50])) == ["IR100 speed = 50%"]


def test_srr_run_and_block_truncation(hrss_notes: Annotator) -> None:
    assert notes(hrss_notes, read(0x03, 0, [0, 5, -3, 0])) == ["SRR[1..4] = 0 5 -3 0"]
    tx = read(0x04, 202, list(range(14)))
    assert notes(hrss_notes, tx) == [
        "IR202..IR215 command returns = 0 1 2 3 4 5 6 7 8 9 10 11 … (+2)"
    ]


def test_unmapped_addresses_give_no_notes(hrss_notes: Annotator) -> None:
    assert notes(hrss_notes, read(0x03, 150, [1, 2])) == []
    assert notes(hrss_notes, pending(encode_read_request(0x03, 150, 2))) == []
    # a read straddling a gap annotates only the mapped part
    assert notes(hrss_notes, read(0x04, 98, [0, 0, 42])) == ["IR100 speed = 42%"]


def test_fc17_and_fc16(hrss_notes: Annotator) -> None:
    req = bytes([0x17]) + (524).to_bytes(2, "big") + (1).to_bytes(2, "big")
    req += (200).to_bytes(2, "big") + (1).to_bytes(2, "big") + bytes([2]) + (1).to_bytes(2, "big")
    # the 0x17 request reads holding registers: R524 is unmapped, so only the write part shows
    assert notes(hrss_notes, pending(req)) == ["R200 = 1 (execute)"]
    req = bytes([0x17]) + (100).to_bytes(2, "big") + (1).to_bytes(2, "big")
    req += (200).to_bytes(2, "big") + (1).to_bytes(2, "big") + bytes([2]) + (0).to_bytes(2, "big")
    assert notes(hrss_notes, pending(req)) == ["R200 = 0 (ready)", "read R100 set speed"]
    tx = answered(req, encode_read_response(0x17, [80]))
    assert notes(hrss_notes, tx) == ["R100 set speed = 80%"]
    mask = bytes([0x16, 0x00, 0xC8, 0x00, 0x00, 0x00, 0x01])
    assert notes(hrss_notes, pending(mask)) == ["R200 = (R200 AND 0x0000) OR 0x0001"]


def test_exception_timeout_unsolicited(hrss_notes: Annotator) -> None:
    tx = answered(encode_read_request(0x04, 524, 1), encode_exception(0x04, 2))
    assert hrss_notes.annotate(tx) == Annotation()
    req = frame(encode_read_request(0x04, 524, 1), False, ROBOT, 1)
    assert hrss_notes.annotate(Transaction(5.0, TxStatus.TIMEOUT, req, None)) == Annotation()
    resp = frame(encode_read_response(0x04, [2]), True, ROBOT, 1)
    assert hrss_notes.annotate(Transaction(5.0, TxStatus.UNSOLICITED, None, resp)) == Annotation()
    echo = frame(encode_write_single(0x06, 200, 1), True, ROBOT, 1)
    tx = Transaction(5.0, TxStatus.UNSOLICITED, None, echo)
    assert notes(hrss_notes, tx) == ["R200 = 1 (execute)"]  # an echo says it all


# ---------------------------------------------------------------------- XEG (Table 56)


def test_xeg_table_56(xeg_only: Annotator) -> None:
    def x(tx: Transaction) -> list[str]:
        return notes(xeg_only, tx)

    assert x(read(0x03, 1536, [2624], GRIPPER, 1)) == ["R1536 gripper model = XEG-64 (2624)"]
    assert x(pending(encode_write_single(0x06, 1552, 1), GRIPPER)) == ["R1552 reset = 1 (Reset)"]
    stroke = encode_write_multiple_request(0x10, 1600, [0, 4600, 5000, 500, 1000, 60, 1])
    assert x(pending(stroke, GRIPPER)) == [
        "R1600 direction = close (0)",
        "R1601 stroke = 46.00 mm",
        "R1602 moving speed = 50.00 mm/s",
        "R1603 gripping stroke = 5.00 mm",
        "R1604 gripping speed = 10.00 mm/s",
        "R1605 gripping force = 60%",
        "R1606 confirm = 1 (parameters set)",
    ]
    assert x(read(0x04, 771, [2, 0, 20, 535], GRIPPER)) == ["IR771 firmware version = V2.0.20.535"]
    assert x(read(0x04, 772, [0, 20], GRIPPER)) == [
        "IR771 firmware version (words 2..3 of 4) = 0 20 (rest not in this read)"
    ]
    assert x(read(0x04, 769, [1], GRIPPER)) == ["IR769 gripper status = Busy (1)"]
    assert x(read(0x04, 769, [3], GRIPPER)) == ["IR769 gripper status = Hold (3)"]


# ---------------------------------------------------------------------- binding and sessions


def test_no_profile_costs_nothing() -> None:
    a = Annotator(ProfileBinding.parse([]))
    tx = pending(encode_write_single(0x05, 0, True))
    first = a.annotate(tx)
    assert first == Annotation() and a.annotate(tx) is first
    assert a.sessions() == {}


def test_binding_per_unit_and_endpoint() -> None:
    a = Annotator(ProfileBinding.parse(["unit:2=xeg", "192.168.0.2:502=hrss"]))
    assert notes(a, read(0x04, 769, [0], GRIPPER, 2)) == ["IR769 gripper status = Idle (0)"]
    assert notes(a, read(0x04, 769, [0], GRIPPER, 1)) == []  # unit 1 on the bus: unbound
    assert notes(a, read(0x04, 524, [2], ROBOT, 1))[0] == "IR524 motion state = Running (2)"
    assert notes(a, read(0x04, 769, [0], ROBOT, 2)) == ["IR769 gripper status = Idle (0)"]


def test_xeg_profile_has_no_session(xeg_only: Annotator) -> None:
    xeg_only.annotate(pending(encode_write_single(0x06, 200, 1), GRIPPER))
    assert xeg_only.sessions() == {}


def test_hrss_session_merged_after_profile_notes(hrss_notes: Annotator) -> None:
    from mbmon.semantics.hrss import HrssSession

    a = Annotator(ProfileBinding.parse(["hrss"]))
    twin = HrssSession(ROBOT, 1)  # fed the same steps: what the session alone says
    # §5.4.5.2: PTP {A1 90} Vel=50% Acc=100% TOOL[1] BASE[2], R201..R226
    ptp = [0, 0, 24464, 1] + [0] * 10 + [50, 100, 1, 2] + [0] * 8
    steps = [
        pending(encode_write_multiple_request(0x10, 201, ptp)),
        pending(encode_write_single(0x06, 200, 1)),
        read(0x04, 200, [1, 0]),
        read(0x04, 524, [2]),
    ]
    saw_command = False
    for tx in steps:
        mine = notes(hrss_notes, tx)
        assert mine  # every step has profile notes
        got = a.annotate(tx)
        own = twin.feed(tx)
        assert list(got.notes[: len(mine)]) == mine
        assert got.notes[len(mine) :] == tuple(own.notes)
        assert got.commands == tuple(own.commands)
        assert got.state == own.state
        saw_command |= bool(got.commands)
    assert saw_command, "the execute should produce a command step"
    sessions = a.sessions()
    assert list(sessions) == [("192.168.0.2:502", 1)]
    # a second connection to the same server shares the session
    again = Stream(3, Transport.TCP, "192.168.0.10:50999", "192.168.0.2:502")
    a.annotate(pending(encode_read_request(0x04, 524, 1), stream=again))
    assert list(a.sessions()) == [("192.168.0.2:502", 1)]


PLC = """\
[profile]
name = "plc"

[[holding_registers]]
name = "flow"
address = 20
type = "f32"
word_order = "high_low"
unit = "l/min"

[[holding_registers]]
name = "gain"
address = 30
scale = 0.25

[[holding_registers]]
name = "count"
address = 40
type = "u32"
word_order = "high_low"
"""


def test_user_profile_float_swapped_words_and_scale(tmp_path: Path) -> None:
    path = tmp_path / "plc.toml"
    path.write_text(PLC, "utf-8")
    a = Annotator(ProfileBinding.parse([str(path)]))
    # IEEE754 10.5 = 0x41280000 (§5.4.4.2), high word first in this device
    assert notes(a, read(0x03, 20, [0x4128, 0x0000])) == ["flow = 10.5 l/min"]
    assert notes(a, read(0x03, 30, [3])) == ["gain = 0.75"]
    assert notes(a, read(0x03, 30, [-7])) == ["gain = -1.75"]
    assert notes(a, read(0x03, 40, [1, 5])) == ["count = 65541"]
    assert notes(a, read(0x03, 40, [1])) == ["count (high word) = 1 (low word not in this read)"]
    assert notes(a, read(0x03, 41, [5])) == ["count (low word) = 5 (high word not in this read)"]
