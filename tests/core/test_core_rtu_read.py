"""``mbmon read --rtu-raw`` on the compiled core (the framer's frames paired and
written by the core) against the reference pipeline with the reference
``RtuDecoder``: the same text and JSON, byte for byte, and the same summary, on the
project's RTU dumps, the real Solis log, libmodbus's session, generated buses (every
function code, noise, broken CRCs, cut frames, timeouts, unsolicited and foreign
answers, broadcasts, Diagnostics 04, malformed answers) and random bytes; the RTU
pairing rules as a byte table; the command's hand-off and its declines."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
from core_diff import REAL, ROOT
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rtu_gen import (
    assert_read_same,
    generated_bus,
    libmodbus_bus,
    paired_bus,
    read_with_core,
    rtu_pairs,
)

from mbmon.protocol.rtu import encode_rtu

CAPTURES = ROOT / "captures"
SOLIS = REAL / "rtu_log__candlerb__solis_packet_log.md"


# ---------------------------------------------------------------- byte tables

_REQ, _ANS = "master → slave", "slave → master"


def _line(index: int, label: str, unit: int, pdu: str, note: str) -> str:
    return f"#{index}  {label}  [u{unit}]  {pdu}  | {note}"


_NO_REQUEST = " (no matching request)"
_LISTEN = "Diagnostics sub-function 4 Force Listen Only Mode = 0"
_ILLEGAL = "Exception 02 Illegal Data Address (Read Coils)"

PAIRING = [
    # (bytes on the bus, the lines the core writes for them)
    (encode_rtu(1, bytes.fromhex("03 00 64 00 02")),
     [_line(0, _REQ, 1, "03 00 64 00 02", "Read Holding Registers 100..101")]),
    (encode_rtu(2, bytes.fromhex("03 04 00 07 00 08")),
     [_line(1, _ANS, 2, "03 04 00 07 00 08", "Read Holding Registers = 7, 8" + _NO_REQUEST)]),
    (encode_rtu(1, bytes.fromhex("04 04 00 07 00 08")),
     [_line(2, _ANS, 1, "04 04 00 07 00 08", "Read Input Registers = 7, 8" + _NO_REQUEST)]),
    (encode_rtu(1, bytes.fromhex("03 04 00 07 00 08")),
     [_line(3, _ANS, 1, "03 04 00 07 00 08", "Read Holding Registers 100..101 = 7, 8")]),
    (encode_rtu(1, bytes.fromhex("06 00 C8 00 01")),
     [_line(4, _REQ, 1, "06 00 C8 00 01", "Write Single Register 200 = 1")]),
    (encode_rtu(0, bytes.fromhex("06 00 C8 00 02")),
     ["#5  -- No response to Write Single Register (record #4)",
      _line(6, _REQ, 0, "06 00 C8 00 02", "Write Single Register 200 = 2")]),
    (encode_rtu(3, bytes.fromhex("08 00 04 00 00")),
     [_line(7, _REQ, 3, "08 00 04 00 00", _LISTEN)]),
    (encode_rtu(3, bytes.fromhex("81 02")),
     [_line(8, _ANS, 3, "81 02", _ILLEGAL + _NO_REQUEST)]),
    (encode_rtu(4, bytes.fromhex("01 00 00 00 03")),
     [_line(9, _REQ, 4, "01 00 00 00 03", "Read Coils 0..2")]),
    (encode_rtu(4, bytes.fromhex("81 02")),
     [_line(10, _ANS, 4, "81 02", _ILLEGAL)]),
    (encode_rtu(4, bytes.fromhex("02 00 00 00 03")),
     [_line(11, _REQ, 4, "02 00 00 00 03", "Read Discrete Inputs 0..2")]),
    (bytes.fromhex("00 FF"),
     ["#12  bus.bin  !! noise, 2 bytes (truncated frame at end of stream): 00 FF",
      "#13  -- No response to Read Discrete Inputs (record #11)"]),
]  # fmt: skip


def test_rtu_pairing_rules_as_a_byte_table(tmp_path) -> None:
    """One pending request per bus: an answer of another unit or code is unsolicited
    and leaves it pending, a new request times it out (a broadcast too, and is never
    pending itself), Diagnostics 04 is never pending, the end times out the last (after the
    framer's own end: the noise it held)."""
    dump = tmp_path / "bus.bin"
    dump.write_bytes(b"".join(adu for adu, _ in PAIRING))
    text = assert_read_same(dump)
    assert text.decode().splitlines() == [line for _, lines in PAIRING for line in lines]
    _, summary = read_with_core(dump, as_json=False)
    assert summary.splitlines()[0] == (
        "11 frames (6 requests, 2 answered, 2 exceptions, 2 unanswered, 3 unsolicited) on 1 streams"
    )


def test_untimed_json_has_no_time_nor_latency_but_the_request_index(tmp_path) -> None:
    dump = tmp_path / "bus.bin"
    dump.write_bytes(b"".join(adu for adu, _ in PAIRING[:4]))
    got, _ = read_with_core(dump, as_json=True)
    last = got.splitlines()[-1]
    assert b'"time":null' in last and b'"tid":null' in last and b'"transport":"rtu"' in last
    assert last.endswith(b'"crc_ok":true,"latency_ms":null,"malformed":null,"request_index":0}')


# ---------------------------------------------------------------- captures


@pytest.mark.parametrize("name", ["hrss_rtu.bin", "sim_rtu.bin"])
def test_project_rtu_dumps(name: str) -> None:
    assert assert_read_same(CAPTURES / name)


def test_real_solis_log_as_a_dump(tmp_path) -> None:
    if not SOLIS.exists():
        pytest.skip(f"{SOLIS.name} absent: ../shared/captures/real is not there")
    frames = []
    for line in SOLIS.read_text().splitlines():
        m = re.fullmatch(r"\s*(?::[0-9.]+\s*)?-([<>])([0-9A-Fa-f]+)\s*", line)
        if m:
            frames.append(bytes.fromhex(m.group(2)))
    dump = tmp_path / "solis.bin"
    dump.write_bytes(b"".join(frames))
    assert len(assert_read_same(dump).splitlines()) >= len(frames)


# ---------------------------------------------------------------- generated


def test_every_function_code_and_libmodbus(tmp_path) -> None:
    dump = tmp_path / "bus.bin"
    dump.write_bytes(b"".join(rtu_pairs()) + b"".join(rtu_pairs(0)) + libmodbus_bus())
    assert_read_same(dump)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_generated_buses(tmp_path, seed: int) -> None:
    dump = tmp_path / "bus.bin"
    dump.write_bytes(generated_bus(seed, 300))
    assert_read_same(dump)


@pytest.mark.parametrize("seed", [4, 5, 6])
def test_pairing_buses(tmp_path, seed: int) -> None:
    dump = tmp_path / "bus.bin"
    dump.write_bytes(paired_bus(seed, 400))
    text = assert_read_same(dump, timeout=0.25)
    assert b"No response to" in text and b"(no matching request)" in text and b"noise" in text


def test_a_dump_of_several_reads_and_an_empty_one(tmp_path) -> None:
    """Frames across the reads (4096 bytes each, and reads of other sizes) and a dump
    with nothing in it."""
    dump = tmp_path / "bus.bin"
    dump.write_bytes(paired_bus(7, 1500))
    assert dump.stat().st_size > 3 * 4096
    assert_read_same(dump)
    short = tmp_path / "short.bin"
    short.write_bytes(paired_bus(8, 60))
    for size in (1, 7, 100):
        assert_read_same(short, read_size=size)
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    assert assert_read_same(empty) == b""


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.binary(max_size=600), st.lists(st.integers(0, 60), max_size=6))
def test_random_bytes_between_frames(tmp_path, noise: bytes, picks: list[int]) -> None:
    pairs = rtu_pairs()
    parts = [pairs[i % len(pairs)] for i in picks]
    cut = len(noise) // 2
    dump = tmp_path / "random.bin"
    dump.write_bytes(noise[:cut] + b"".join(parts) + noise[cut:])
    assert_read_same(dump)


_EDGES = st.sampled_from([0, 1, 2, 15, 16, 17, 120, 121, 122, 125, 126, 0xFFFF])
_ADDRESSES = st.sampled_from([0, 1, 100, 0xFF80, 0xFFFE, 0xFFFF])


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    st.lists(
        st.tuples(_ADDRESSES, _EDGES, _ADDRESSES, _EDGES, st.integers(-2, 2), st.integers(-2, 2)),
        min_size=1,
        max_size=6,
    ),
    st.randoms(use_true_random=False),
)
def test_read_write_multiple_registers_at_the_edges(tmp_path, exchanges, rng) -> None:
    """0x17, which the core writes itself on a bus: counts and addresses at the spec's
    limits and past them, write byte counts that disagree, answers whose byte count
    breaks the request's read count, unpaired answers."""
    parts = []
    for address, count, waddr, wcount, off_write, off_read in exchanges:
        words = rng.randbytes(2 * min(wcount, 127))
        wbc = max(0, min(255, 2 * wcount + off_write))
        request = bytes([0x17]) + b"".join(
            v.to_bytes(2, "big") for v in (address, count, waddr, wcount)
        )
        parts.append(encode_rtu(5, request + bytes([wbc]) + words[:wbc]))
        rbc = max(0, min(250, 2 * min(count, 125) + off_read))
        parts.append(encode_rtu(5, bytes([0x17, rbc]) + rng.randbytes(rbc)))
        if off_read == 2:
            parts.append(encode_rtu(5, bytes([0x17, 4]) + rng.randbytes(4)))  # unsolicited
    dump = tmp_path / "rw.bin"
    dump.write_bytes(b"".join(parts))
    assert_read_same(dump)


# ---------------------------------------------------------------- the command


def _mbmon(
    args: list[str], pure: bool, stdin: bytes | None = None
) -> subprocess.CompletedProcess[bytes]:
    env = dict(os.environ)
    env.pop("MBMON_NO_EXTENSIONS", None)
    if pure:
        env["MBMON_NO_EXTENSIONS"] = "1"
    return subprocess.run(
        [sys.executable, "-m", "mbmon", *args],
        capture_output=True,
        env=env,
        cwd=ROOT,
        timeout=300,
        input=stdin,
    )


def test_the_command_reads_a_dump_on_the_core_and_says_so(tmp_path) -> None:
    read_with_core(CAPTURES / "sim_rtu.bin", as_json=False)  # skips without the core
    dump = tmp_path / "bus.bin"
    dump.write_bytes(paired_bus(9, 300))
    for extra in ([], ["--json"], ["-q"]):
        args = ["read", "--rtu-raw", str(dump), "--debug-core", *extra]
        fast = _mbmon(args, pure=False)
        pure = _mbmon(args, pure=True)
        assert fast.returncode == pure.returncode == 0
        assert b"core: the compiled core read the input" in fast.stderr
        assert fast.stdout == pure.stdout
        assert fast.stderr.splitlines()[1:] == pure.stderr.splitlines()[2:]


@pytest.mark.parametrize(
    ("extra", "why"),
    [
        (["-w", "x.mcap"], b"-w with --rtu-raw"),
        (["--profile", "hrss"], b"--profile with --rtu-raw"),
    ],
)
def test_what_the_core_declines_for_a_dump(tmp_path, extra: list[str], why: bytes) -> None:
    read_with_core(CAPTURES / "sim_rtu.bin", as_json=False)
    extra = [str(tmp_path / a) if a == "x.mcap" else a for a in extra]
    args = ["read", "--rtu-raw", "captures/sim_rtu.bin", "--debug-core", *extra]
    fast = _mbmon(args, pure=False)
    assert b"core: declined (" + why in fast.stderr
    assert fast.stdout == _mbmon(args, pure=True).stdout


def test_a_dump_whose_name_is_no_utf8_is_declined_and_read_alike(tmp_path) -> None:
    """The lines name the bus after its file: a name with bytes that are no UTF-8 is
    the reference's to escape (it is declined before a byte is written)."""
    read_with_core(CAPTURES / "sim_rtu.bin", as_json=False)
    odd = os.fsencode(tmp_path) + b'/bus\xff"q.bin'
    with open(odd, "wb") as f:
        f.write((CAPTURES / "sim_rtu.bin").read_bytes() + b"\x00\xff")  # noise names the bus
    args = ["read", "--rtu-raw", os.fsdecode(odd), "--debug-core"]
    fast = _mbmon(args, pure=False)
    assert b"core: declined (a dump whose file name is not UTF-8)" in fast.stderr
    pure = _mbmon(args, pure=True)
    assert fast.returncode == pure.returncode == 0
    assert fast.stdout == pure.stdout and b"bus\\udcff" in fast.stdout


def test_a_dump_on_stdin_is_declined_and_read_alike() -> None:
    read_with_core(CAPTURES / "sim_rtu.bin", as_json=False)
    data = (CAPTURES / "sim_rtu.bin").read_bytes()
    args = ["read", "--rtu-raw", "-", "--debug-core"]
    fast = _mbmon(args, pure=False, stdin=data)
    assert b"core: declined (a pipe, FIFO or device as input" in fast.stderr
    assert fast.stdout == _mbmon(args, pure=True, stdin=data).stdout
