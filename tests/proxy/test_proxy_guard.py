"""The proxy's write guard and client filter: pure decisions, tested at range edges."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from mbmon.protocol.functions import FUNCTIONS, FunctionCode, register, unregister
from mbmon.protocol.pdu import (
    decode_pdu,
    encode_read_request,
    encode_write_multiple_request,
    encode_write_single,
)
from mbmon.proxy.guard import (
    KNOWN_READS,
    ClientFilter,
    Guard,
    GuardSpecError,
    WriteSpec,
    WriteTarget,
    is_write,
    parse_spec,
    write_target,
)


def req(hex_pdu: str | bytes):
    data = bytes.fromhex(hex_pdu) if isinstance(hex_pdu, str) else hex_pdu
    return decode_pdu(data, False)


HR6 = lambda a: req(encode_write_single(6, a, 1))  # noqa: E731
COIL5 = lambda a: req(encode_write_single(5, a, True))  # noqa: E731
HR10 = lambda a, n: req(encode_write_multiple_request(0x10, a, [0] * n))  # noqa: E731
COIL15 = lambda a, n: req(encode_write_multiple_request(0x0F, a, [1] * n))  # noqa: E731

# every writing function code, as a request PDU (hex)
WRITES = {
    0x05: "05 00 10 FF 00",
    0x06: "06 00 10 00 2A",
    0x0F: "0F 00 10 00 03 01 05",
    0x10: "10 00 10 00 02 04 00 01 00 02",
    0x15: "15 09 06 00 04 00 07 00 01 12 34",
    0x16: "16 00 10 00 F2 00 25",
    0x17: "17 00 00 00 02 00 10 00 01 02 00 2A",
}
READS = {
    0x01: "01 00 00 00 08",
    0x02: "02 00 00 00 08",
    0x03: "03 00 00 00 0A",
    0x04: "04 00 00 00 0A",
    0x07: "07",
    0x08: "08 00 00 12 34",
    0x11: "11",
    0x2B: "2B 0E 01 00",
}


@pytest.mark.parametrize("fc,pdu", sorted(WRITES.items()))
def test_read_only_refuses_every_writing_code(fc: int, pdu: str) -> None:
    guard = Guard.from_options(True, [], [])
    verdict = guard.check(1, req(pdu))
    assert verdict is not None and verdict.rule == "read-only"
    assert verdict.info["fc"] == fc and verdict.info["unit"] == 1
    assert is_write(fc)


@pytest.mark.parametrize("fc,pdu", sorted(READS.items()))
def test_read_only_lets_reads_through(fc: int, pdu: str) -> None:
    assert Guard.from_options(True, [], []).check(1, req(pdu)) is None
    assert not is_write(fc)


def test_targets_of_each_code() -> None:
    t = {fc: write_target(req(p)) for fc, p in WRITES.items()}
    assert (t[0x05].table, t[0x05].first, t[0x05].last) == ("coil", 16, 16)
    assert (t[0x06].table, t[0x06].first, t[0x06].last) == ("hr", 16, 16)
    assert (t[0x0F].table, t[0x0F].first, t[0x0F].last) == ("coil", 16, 18)
    assert (t[0x10].table, t[0x10].first, t[0x10].last) == ("hr", 16, 17)
    assert (t[0x15].table, t[0x15].first) == (None, None)
    assert (t[0x16].table, t[0x16].first, t[0x16].last) == ("hr", 16, 16)
    # 0x17: the write part (R16), not the read part (R0..R1)
    assert (t[0x17].table, t[0x17].first, t[0x17].last, t[0x17].count) == ("hr", 16, 16, 1)
    assert write_target(req(encode_read_request(3, 0, 10))) is None


def test_truncated_write_counts_as_the_whole_table() -> None:
    target = write_target(req("10 00 10"))  # no count: unknown range
    assert target is not None and (target.first, target.last) == (0, 0xFFFF)
    guard = Guard.from_options(False, ["hr:16-17"], [])
    assert guard.check(1, req("10 00 10")) is not None


@pytest.mark.parametrize(
    "address,allowed",
    [(99, False), (100, True), (150, True), (251, True), (252, False)],
)
def test_allow_range_edges_single(address: int, allowed: bool) -> None:
    guard = Guard.from_options(True, ["hr:100", "hr:101-251"], [])
    assert (guard.check(1, HR6(address)) is None) is allowed


@pytest.mark.parametrize(
    "address,count,allowed",
    [
        (100, 123, True),  # 100..222, covered by the two specs together
        (99, 2, False),  # starts one below
        (250, 2, True),  # ends on the edge
        (250, 3, False),  # one past the edge
        (300, 1, False),
    ],
)
def test_allow_multiple_must_be_covered(address: int, count: int, allowed: bool) -> None:
    guard = Guard.from_options(False, ["hr:100", "hr:101-251"], [])
    verdict = guard.check(1, HR10(address, count))
    assert (verdict is None) is allowed
    if verdict is not None:
        assert verdict.rule == "not in --allow-write"


@pytest.mark.parametrize("address,denied", [(6, False), (7, True), (8, False)])
def test_deny_beats_allow_at_edges(address: int, denied: bool) -> None:
    guard = Guard.from_options(False, ["coil:0-15"], ["coil:7"])
    verdict = guard.check(1, COIL5(address))
    assert (verdict is not None) is denied
    if denied:
        assert verdict.rule == "deny-write coil:7"
        assert verdict.info == {
            "rule": "deny-write coil:7",
            "fc": 5,
            "unit": 1,
            "address": 7,
            "count": 1,
        }


def test_deny_hits_a_multiple_write_that_overlaps_one_address() -> None:
    guard = Guard.from_options(False, [], ["coil:0-7"])
    assert guard.check(1, COIL15(7, 4)) is not None  # 7..10 overlaps 7
    assert guard.check(1, COIL15(8, 4)) is None  # 8..11 does not
    assert guard.check(1, HR6(3)) is None  # another table


def test_unit_terms() -> None:
    guard = Guard.from_options(True, ["unit:2"], ["unit:3,hr:10-19"])
    assert guard.check(2, HR10(0, 100)) is None  # everything on unit 2
    assert guard.check(1, HR6(0)) is not None
    assert guard.check(2, req(WRITES[0x15])) is None  # a unit-only spec covers file records
    deny_only = Guard.from_options(False, [], ["unit:3,hr:10-19"])
    assert deny_only.check(3, HR6(19)) is not None
    assert deny_only.check(3, HR6(20)) is None
    assert deny_only.check(4, HR6(15)) is None
    assert deny_only.check(3, COIL5(15)) is None


def test_file_records_only_unit_specs_apply() -> None:
    pdu = req(WRITES[0x15])
    assert Guard.from_options(False, ["hr:0-65535"], []).check(1, pdu) is not None
    assert Guard.from_options(False, [], ["hr:0-65535"]).check(1, pdu) is None
    assert Guard.from_options(False, [], ["unit:1"]).check(1, pdu) is not None


def test_no_options_no_guard() -> None:
    guard = Guard.from_options(False, [], [])
    assert not guard.active
    assert all(guard.check(1, req(p)) is None for p in WRITES.values())
    assert guard.describe() == "off"


def test_exception_code_and_message() -> None:
    guard = Guard.from_options(True, [], [], exception_code=4)
    assert guard.exception_code == 4
    verdict = guard.check(7, HR10(200, 3))
    assert verdict is not None
    assert verdict.message == "refused 0x10 write R200..202 on unit 7 (read-only)"
    with pytest.raises(GuardSpecError):
        Guard.from_options(True, [], [], exception_code=0)


@pytest.mark.parametrize(
    "text,spec",
    [
        ("hr:100", WriteSpec("hr:100", None, "hr", 100, 100)),
        ("hr:200-251", WriteSpec("hr:200-251", None, "hr", 200, 251)),
        ("coil:0-7", WriteSpec("coil:0-7", None, "coil", 0, 7)),
        ("unit:2", WriteSpec("unit:2", (2, 2), None, 0, 0xFFFF)),
        ("unit:2,hr:0x10-0x1F", WriteSpec("unit:2,hr:0x10-0x1F", (2, 2), "hr", 16, 31)),
        (" HR:65535 ", WriteSpec("HR:65535", None, "hr", 65535, 65535)),
    ],
)
def test_parse_spec(text: str, spec: WriteSpec) -> None:
    assert parse_spec(text) == spec


@pytest.mark.parametrize(
    "text,words",
    [
        ("", "empty"),
        ("hr", "NAME:A"),
        ("hr:", "NAME:A"),
        ("ir:3", "unknown term"),
        ("hr:x", "not a number"),
        ("hr:10-5", "backwards"),
        ("hr:65536", "outside"),
        ("unit:256", "outside"),
        ("hr:1,coil:2", "more than one table"),
        ("unit:1,unit:2", "more than one unit"),
    ],
)
def test_bad_specs_say_why(text: str, words: str) -> None:
    with pytest.raises(GuardSpecError, match=words):
        parse_spec(text)


def test_client_filter() -> None:
    f = ClientFilter(["10.0.0.0/24", "127.0.0.1", "::1"])
    assert f.allows("10.0.0.0") and f.allows("10.0.0.255")
    assert not f.allows("10.0.1.0")
    assert f.allows("127.0.0.1") and not f.allows("127.0.0.2")
    assert f.allows("::ffff:10.0.0.7")  # IPv4-mapped
    assert f.allows("::1") and not f.allows("::2")
    assert not f.allows("not-an-address")
    assert ClientFilter([]).allows("192.0.2.1")
    with pytest.raises(GuardSpecError, match="CIDR"):
        ClientFilter(["10.0.0.0/33"])


# --------------------------------------------------------------------------- malformed writes

#: writes whose byte count, quantity and length disagree, or whose range runs past
#: 0xFFFF: (request PDU, why), each next to R200..R251 / coils 200..251
MALFORMED_WRITES = [
    ("10 00 FB 00 01 04 00 01 00 02", "byte count 4 but 1 registers need 2"),
    ("10 00 FB 00 02 02 00 01", "byte count 2 but 2 registers need 4"),
    ("10 00 FA 00 01 02 00 01 00 02", "byte count 2 but 4 data bytes"),
    ("0F 00 C8 00 08 02 FF FF", "byte count 2 but 8 bits need 1"),
    ("17 00 00 00 01 00 FB 00 01 04 00 01 00 02", "write byte count 4 but 1 registers"),
    ("10 FF FF 00 02 04 00 01 00 02", "exceeds 65536"),
    ("0F FF FE 00 08 01 FF", "exceeds 65536"),
    ("17 00 00 00 01 FF FF 00 02 04 00 01 00 02", "exceeds 65536"),
    ("10 00 C8 00 00 00", "quantity"),
]


@pytest.mark.parametrize(("pdu", "why"), MALFORMED_WRITES)
@pytest.mark.parametrize(
    "options",
    [
        (True, ["hr:200-251", "coil:200-251", "hr:0-65535"], []),
        (False, ["hr:0-65535", "coil:0-65535"], []),
        (False, [], ["unit:9"]),  # a deny spec that does not touch it: still malformed
    ],
    ids=["read-only+allow", "allow-all", "deny-other"],
)
def test_malformed_write_is_refused_whatever_the_specs(
    pdu: str, why: str, options: tuple[bool, list[str], list[str]]
) -> None:
    request = req(pdu)
    if why == "quantity":  # quantity 0: the decoder names it its own way
        assert request.malformed is not None
    else:
        assert why in (request.malformed or "")
    verdict = Guard.from_options(*options).check(1, request)
    assert verdict is not None and verdict.rule == "malformed"
    assert verdict.info["reason"] == request.malformed
    assert "malformed" in verdict.message


@pytest.mark.parametrize(
    "pdu",
    [
        "10 00 FB 00 01 02 00 01",  # R251, one register: the last allowed
        "10 00 FA 00 02 04 00 01 00 02",  # R250..R251
        "0F 00 C8 00 08 01 FF",  # coils 200..207, 8 bits in one byte
        "17 00 00 00 01 00 FB 00 01 02 00 01",
    ],
)
def test_well_formed_writes_at_the_edge_pass(pdu: str) -> None:
    guard = Guard.from_options(True, ["hr:200-251", "coil:200-251"], [])
    assert guard.check(1, req(pdu)) is None


def test_no_guard_forwards_malformed_writes_untouched() -> None:
    """Without any guard option the proxy never alters traffic."""
    for pdu, _why in MALFORMED_WRITES:
        assert Guard.from_options(False, [], []).check(1, req(pdu)) is None


# --------------------------------------------------------------------------- read-only allow-list

#: request PDU -> passes --read-only
READ_ONLY_TABLE = {
    "01 00 00 00 08": True,
    "02 00 00 00 08": True,
    "03 00 00 00 0A": True,
    "04 00 00 00 0A": True,
    "07": True,
    "0B": True,
    "0C": True,
    "11": True,
    "14 07 06 00 04 00 01 00 02": True,
    "18 04 DE": True,
    "2B 0E 01 00": True,
    "08 00 00 12 34": True,  # Return Query Data
    "08 00 02 00 00": True,  # Return Diagnostic Register
    "08 00 0B 00 00": True,  # Return Bus Message Count
    "08 00 12 00 00": True,  # Return Bus Character Overrun Count
    "08 00 01 00 00": False,  # Restart Communications
    "08 00 01 FF 00": False,
    "08 00 04 00 00": False,  # Force Listen Only Mode
    "08 00 03 3A 00": False,  # Change ASCII Input Delimiter
    "08 00 0A 00 00": False,  # Clear Counters and Diagnostic Register
    "08 00 14 00 00": False,  # Clear Overrun Counter and Flag
    "08 00": False,  # too short to say which
    "2B 0D 00 00": False,  # CANopen General Reference
    "41 00 01": False,  # user-defined 65
    "48": False,  # user-defined 72
    "64 01 02": False,  # user-defined 100
    "6E": False,  # user-defined 110
    "09": False,  # unknown to the spec
    "7F 00": False,
}


@pytest.mark.parametrize(("pdu", "passes"), sorted(READ_ONLY_TABLE.items()))
def test_read_only_is_an_allow_list(pdu: str, passes: bool) -> None:
    guard = Guard.from_options(True, [], [])
    verdict = guard.check(1, req(pdu))
    assert (verdict is None) is passes
    assert (guard.check_raw(1, bytes.fromhex(pdu)) is None) is passes
    if verdict is not None:
        assert verdict.rule == "read-only"
        assert verdict.info["fc"] == bytes.fromhex(pdu)[0]
        assert "--allow-fc" in verdict.message


def test_read_only_refusal_names_the_sub_function() -> None:
    verdict = Guard.from_options(True, [], []).check(1, req("08 00 04 00 00"))
    assert verdict is not None
    assert verdict.info["sub_function"] == 4
    assert "0x08/0x04" in verdict.message


def test_without_read_only_codes_that_do_not_write_pass() -> None:
    for guard in (
        Guard.from_options(False, ["hr:200-251"], []),
        Guard.from_options(False, [], ["hr:0-10"]),
    ):
        for pdu in READ_ONLY_TABLE:
            assert guard.check(1, req(pdu)) is None, pdu


@pytest.mark.parametrize(
    ("allow_fc", "pdu", "passes"),
    [
        (["8/1"], "08 00 01 00 00", True),
        (["8/1"], "08 00 04 00 00", False),
        (["0x08/0x0004"], "08 00 04 00 00", True),
        (["08"], "08 00 0A 00 00", True),
        (["65-72"], "41 00", True),
        (["65-72"], "48", True),
        (["65-72"], "49", False),
        (["0x64-0x6E"], "6E", True),
        (["0x2B/0x0D"], "2B 0D 00 00", True),
        (["0x2B/0x0D"], "2B 0E 01 00", True),  # a known read anyway
        (["100"], "64 01 02", True),
        (["100"], "41 00", False),
    ],
)
def test_allow_fc_opens_a_named_code(allow_fc: list[str], pdu: str, passes: bool) -> None:
    guard = Guard.from_options(True, [], [], allow_fc=allow_fc)
    assert (guard.check(1, req(pdu)) is None) is passes
    assert "allow-fc" in guard.describe()


def test_allow_fc_never_opens_writes() -> None:
    guard = Guard.from_options(True, [], [], allow_fc=["65-72"])
    assert guard.check(1, req("06 00 10 00 2A")) is not None


@pytest.mark.parametrize(
    ("values", "read_only", "words"),
    [
        (["6"], True, "writes; writes are opened by --allow-write"),
        (["1-16"], True, "writes"),
        (["x"], True, "is not a number"),
        (["0"], True, "no function code 0"),
        (["200"], True, "outside 0..127"),
        (["72-65"], True, "backwards"),
        (["3/1"], True, "CODE/SUB names a Diagnostics"),
        (["8/0x10000"], True, "outside 0..65535"),
        (["65"], False, "without --read-only"),
    ],
)
def test_bad_allow_fc_says_why(values: list[str], read_only: bool, words: str) -> None:
    with pytest.raises(GuardSpecError, match=words):
        Guard.from_options(read_only, [], [], allow_fc=values)


# --------------------------------------------------------------------------- the table decides

#: A user-defined read, registered the way tests/protocol/test_new_function_code.py
#: does it: 0x41 reads holding registers like 0x03.
TOY_READ = FunctionCode(
    0x41, "Toy Read", 5, (1, 2), "holding_register", read=True, shape="read", max_count=125
)
#: A user-defined write: 0x42 writes holding registers like 0x10.
TOY_WRITE = FunctionCode(
    0x42, "Toy Write", (5, 6), 5, "holding_register", writes=True, shape="write_multiple",
    max_count=123,
)  # fmt: skip


@pytest.fixture
def toy_codes() -> Iterator[None]:
    assert 0x41 not in FUNCTIONS and 0x42 not in FUNCTIONS
    register(TOY_READ)
    register(TOY_WRITE)
    try:
        yield
    finally:
        unregister(0x41)
        unregister(0x42)


def test_read_only_refuses_an_unregistered_user_code() -> None:
    """Before the table knows 0x41, ``--read-only`` refuses it (not a known read)."""
    guard = Guard.from_options(True, [], [])
    verdict = guard.check_raw(1, bytes.fromhex("41 00 10 00 02"))
    assert verdict is not None and verdict.rule == "read-only"
    assert 0x41 not in KNOWN_READS


def test_a_code_registered_as_a_read_passes_read_only(toy_codes: None) -> None:
    """Registered as a read in the function-code table, 0x41 is a known read to the
    guard: ``--read-only`` forwards it, on the fast path and decoded alike."""
    guard = Guard.from_options(True, [], [])
    assert KNOWN_READS[0x41] is None
    assert guard.check_raw(1, bytes.fromhex("41 00 10 00 02")) is None
    assert guard.check(1, req("41 00 10 00 02")) is None
    assert not is_write(0x41) and write_target(req("41 00 10 00 02")) is None


def test_a_code_registered_as_a_write_is_judged_as_a_write(toy_codes: None) -> None:
    """Registered as a holding-register write, 0x42 is judged by the write specs from
    its row (table, shape: ``count`` registers from its address), and ``--allow-fc``
    cannot open it."""
    pdu = req("42 00 10 00 02 04 00 01 00 02")
    assert is_write(0x42)
    assert write_target(pdu) == WriteTarget(0x42, "hr", 16, 17)
    allow = Guard.from_options(True, ["hr:16-17"], [])
    assert allow.check(1, pdu) is None
    narrow = Guard.from_options(True, ["hr:16"], [])
    verdict = narrow.check(1, pdu)
    assert verdict is not None and verdict.rule == "read-only"
    assert (verdict.info["address"], verdict.info["count"]) == (16, 2)
    with pytest.raises(GuardSpecError, match="0x42 writes"):
        Guard.from_options(True, [], [], allow_fc=["0x42"])
    # unregistered again, the same bytes are an unknown code: not a write
    unregister(0x42)
    assert not is_write(0x42) and write_target(pdu) is None
