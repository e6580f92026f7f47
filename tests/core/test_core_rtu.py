"""The compiled RTU framer (``mbmon.core._rtu``) against the reference ``RtuDecoder``:
the same frames, noise runs with the same reasons, malformed flags and times, out of
the same calls, on the project's RTU captures, the real RTU log, generated buses,
cuts at every byte, random chunkings and random bytes; and ``mbmon read`` on RTU
input byte for byte the same with the core and forced pure."""

from __future__ import annotations

import os
import random
import re
import struct
import subprocess
import sys

import pytest
from core_diff import REAL, ROOT, require_core
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rtu_gen import (
    STREAM,
    chunked,
    every_size,
    generated_bus,
    libmodbus_bus,
    make_core,
    rtu_pairs,
    run,
    same,
)

from mbmon import core
from mbmon.model import Direction, Frame, Noise
from mbmon.protocol.functions import FunctionCode, register, unregister
from mbmon.protocol.rtu import NOISE_CAP, RtuDecoder, encode_rtu

CAPTURES = ROOT / "captures"
SOLIS = REAL / "rtu_log__candlerb__solis_packet_log.md"
LIBMODBUS_BAD = bytes.fromhex("11 10 01 60 00 00 00 02 2B 00 01 00 64 8C 88")


def _items(out: list[list[object]]) -> list[object]:
    return [x for step in out for x in step if isinstance(x, Frame | Noise)]


# ---------------------------------------------------------------- byte tables


def test_libmodbus_quantity_zero_write_is_one_malformed_frame() -> None:
    """libmodbus's write of quantity 0 with 6 data bytes: CRC-valid, fields disagree."""
    answer = bytes.fromhex("11 90 03 0D C4")
    out = _items(same(chunked(LIBMODBUS_BAD + answer, [])))
    assert [type(x).__name__ for x in out] == ["Frame", "Frame"]
    first = out[0]
    assert isinstance(first, Frame) and first.raw == LIBMODBUS_BAD
    assert first.direction is Direction.C2S and first.pdu.malformed


def test_bad_crc_then_good_is_one_noise_run_with_its_reason() -> None:
    bad = bytes.fromhex("11 03 01 60 00 01 87 79")
    good = bytes.fromhex("11 03 01 60 00 01 87 78")
    out = _items(same(chunked(bad + good, [])))
    assert isinstance(out[0], Noise) and out[0].raw == bad
    assert out[0].reason == "no valid frame (bad CRC)"
    assert isinstance(out[1], Frame) and out[1].raw == good


def test_every_function_code_and_exception() -> None:
    data = b"".join(rtu_pairs())
    out = _items(same(every_size(data, 4096)))
    # gen.py's pairs include malformed PDUs on purpose: most are frames, all alike
    assert sum(isinstance(x, Frame) for x in out) > len(rtu_pairs()) * 3 // 4


def test_every_function_code_cut_at_every_byte() -> None:
    data = b"".join(rtu_pairs())
    for cut in range(1, len(data)):
        same(chunked(data, [cut]))


def test_libmodbus_session_cut_at_every_byte() -> None:
    data = libmodbus_bus()
    for cut in range(1, len(data)):
        same(chunked(data, [cut], ts=lambda i: 10.0 + i))


def test_a_scan_across_an_exception_answer_of_code_zero() -> None:
    """A CRC scan (code 0x41, no predictable length) whose match holds an exception
    answer with exception code 0 followed by a read request: whether that answer is
    a frame of its own decides whether the scan swallows frames. The framer follows
    the reference's ``RtuBounds._standalone`` on it, whichever rule it has."""
    exc0 = encode_rtu(0x11, b"\x83\x00")
    req = encode_rtu(0x11, bytes.fromhex("0300000001"))
    scanned = encode_rtu(0x01, b"\x41" + exc0 + req + b"\x00\x00")
    for size in (1, 4096):
        same(every_size(scanned + req, size))


@pytest.mark.parametrize("size", [1, 2, 3, 7, 64, 4096])
def test_libmodbus_session_in_reads_of_every_size(size: int) -> None:
    same(every_size(libmodbus_bus(), size))


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("size", [1, 5, 13, 256, 4096])
def test_generated_buses(seed: int, size: int) -> None:
    same(every_size(generated_bus(seed), size))


def test_noise_longer_than_the_cap_is_split_alike() -> None:
    junk = bytes(NOISE_CAP + 1000)  # function code 0 everywhere: never a frame
    data = encode_rtu(1, b"\x03\x00\x00\x00\x01") + junk + encode_rtu(1, b"\x03\x02\x00\x07")
    out = _items(same(every_size(data, 8192)))
    assert [len(x.raw) for x in out if isinstance(x, Noise)] == [NOISE_CAP, 1000]


@pytest.mark.parametrize("direction", [Direction.C2S, Direction.S2C])
def test_one_direction_of_rtu_over_tcp(direction: Direction) -> None:
    pairs = rtu_pairs()
    data = b"".join(pairs[0 if direction is Direction.C2S else 1 :: 2])
    for size in (1, 9, 4096):
        same(every_size(data + generated_bus(3, 40), size), direction)


def test_silence_ticks_reset_and_times() -> None:
    """Without a baud rate, ``silence`` seconds after the last byte ticks settle what is
    held (the end of a frame cut short, noise), and a reset reports the buffer."""
    data = generated_bus(11, 120)
    rng = random.Random(2)
    steps: list[tuple[object, ...]] = []
    ref = RtuDecoder(STREAM, Direction.BUS, silence=0.5)
    t = 100.0
    pos = 0
    while pos < len(data):
        n = rng.randint(1, 40)
        steps.append(("feed", data[pos : pos + n], t))
        run(ref, [steps[-1]])
        pos += n
        roll = rng.random()
        if roll < 0.2 and ref.next_deadline() is not None:
            steps.append(("tick", ref.next_deadline()))
            run(ref, [steps[-1]])
        elif roll < 0.25:
            steps.append(("reset", t))
            run(ref, [steps[-1]])
        t += rng.choice((0.01, 0.2, 0.6, 2.0))
    steps.append(("flush", t))
    same(steps, silence=0.5)


def test_real_solis_log_as_a_bus() -> None:
    if not SOLIS.exists():
        pytest.skip(f"{SOLIS.name} absent: ../shared/captures/real is not there")
    frames = []
    for line in SOLIS.read_text().splitlines():
        m = re.fullmatch(r"\s*(?::[0-9.]+\s*)?-([<>])([0-9A-Fa-f]+)\s*", line)
        if m:
            frames.append(bytes.fromhex(m.group(2)))
    assert len(frames) == 42
    data = b"".join(frames)
    for size in (1, 13, 4096):
        out = _items(same(every_size(data, size)))
        assert [x.raw for x in out] == frames


@pytest.mark.parametrize("name", ["hrss_rtu.bin", "sim_rtu.bin"])
def test_project_rtu_dumps(name: str) -> None:
    data = (CAPTURES / name).read_bytes()
    for size in (1, 7, 4096):
        same(every_size(data, size))


def test_a_code_registered_at_run_time_is_framed_alike() -> None:
    """``register`` brings the compiled framer's length tables up to date too."""
    make_core()
    spec = FunctionCode(0x41, "Vendor read", request_length=5, response_length=(1, 2))
    req = encode_rtu(2, b"\x41\x00\x10\x00\x02")
    resp = encode_rtu(2, b"\x41\x04\x00\x01\x00\x02")
    register(spec)
    try:
        out = _items(same(every_size(req + resp + req + resp, 3)))
        assert [x.raw for x in out] == [req, resp, req, resp]
    finally:
        unregister(0x41)
    same(every_size(req + resp, 3))


# ---------------------------------------------------------------- packed output


def test_packed_output_is_the_frames_without_objects() -> None:
    data = generated_bus(4, 300)
    ref = RtuDecoder(STREAM, Direction.BUS)
    expected = _items(run(ref, every_size(data, 512)))
    framer = make_core()
    for step in every_size(data, 512):
        if step[0] == "feed":
            framer.push(step[1], step[2])
        else:
            framer.push_flush(step[1])
    records, raw, noise = framer.take()
    assert framer.pending_records == 0
    got: list[object] = []
    for kind, _pad, length, offset, ts in struct.iter_unpack("<BBHId", records):
        if kind == 2:
            got.append(noise[offset])
        else:
            adu = raw[offset : offset + length]
            got.append((ts, Direction.S2C if kind else Direction.C2S, adu))
    assert got == [x if isinstance(x, Noise) else (x.ts, x.direction, x.raw) for x in expected]


# ---------------------------------------------------------------- hypothesis

FRAMES = st.sampled_from([*rtu_pairs(), LIBMODBUS_BAD, bytes.fromhex("11 90 03 0D C4")])
PIECES = st.lists(
    st.one_of(FRAMES, FRAMES, FRAMES, st.binary(min_size=1, max_size=12)), max_size=40
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(pieces=PIECES, data=st.data())
def test_random_buses_in_random_reads(pieces: list[bytes], data: st.DataObject) -> None:
    stream = b"".join(pieces)
    cuts = sorted(set(data.draw(st.lists(st.integers(0, max(0, len(stream))), max_size=30))))
    same(chunked(stream, cuts))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(raw=st.binary(max_size=600), data=st.data())
def test_random_bytes_in_random_reads(raw: bytes, data: st.DataObject) -> None:
    cuts = sorted(set(data.draw(st.lists(st.integers(0, max(0, len(raw))), max_size=20))))
    same(chunked(raw, cuts))
    same(chunked(raw, cuts), Direction.S2C)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    pieces=PIECES,
    events=st.lists(
        st.tuples(st.sampled_from(("feed", "feed", "feed", "tick", "reset")), st.floats(0, 1)),
        min_size=1,
        max_size=30,
    ),
    direction=st.sampled_from([Direction.BUS, Direction.C2S]),
)
def test_random_reads_ticks_and_resets(
    pieces: list[bytes], events: list[tuple[str, float]], direction: Direction
) -> None:
    """Reads at random times, ticks (``silence`` 0.3 s) and resets between them."""
    stream = b"".join(pieces)
    steps: list[tuple[object, ...]] = []
    t = 50.0
    pos = 0
    for how, x in events:
        t += x
        if how == "feed" and pos < len(stream):
            n = 1 + int(x * 40)
            steps.append(("feed", stream[pos : pos + n], t))
            pos += n
        elif how == "tick":
            steps.append(("tick", t))
        elif how == "reset":
            steps.append(("reset", t))
    steps.append(("flush", t + 1))
    same(steps, direction, silence=0.3)


# ---------------------------------------------------------------- declines, wiring


def test_a_baud_rate_is_declined_before_any_framing() -> None:
    require_core()
    assert core.rtu_decoder(STREAM, Direction.BUS, baudrate=9600) is None
    assert "baud rate" in str(core.rtu_decline(9600))
    from mbmon.core import _rtu

    with pytest.raises(ValueError, match="baud rate"):
        _rtu.RtuCore(STREAM, Direction.BUS, 9600)


def test_the_pipeline_frames_rtu_on_the_core_without_a_baud_rate() -> None:
    require_core()
    make_core()
    from mbmon.model import Transport
    from mbmon.pipeline import PipelineConfig, decoder_entry

    entry = decoder_entry(Transport.RTU)
    assert type(entry.make(STREAM, Direction.BUS, PipelineConfig())).__name__ == "RtuCore"
    timed = entry.make(STREAM, Direction.BUS, PipelineConfig(baudrate=9600))
    assert isinstance(timed, RtuDecoder)


def _mbmon(args: list[str], pure: bool) -> subprocess.CompletedProcess[bytes]:
    env = dict(os.environ)
    env.pop("MBMON_NO_EXTENSIONS", None)
    if pure:
        env["MBMON_NO_EXTENSIONS"] = "1"
    return subprocess.run(
        [sys.executable, "-m", "mbmon", *args], capture_output=True, env=env, cwd=ROOT, timeout=300
    )


@pytest.mark.parametrize(
    "args",
    [
        ["read", "--rtu-raw", "captures/hrss_rtu.bin"],
        ["read", "--rtu-raw", "captures/sim_rtu.bin", "--json"],
        ["read", "--rtu-raw", "captures/hrss_rtu.bin", "--profile", "hrss"],
        ["read", "captures/sim_rtu.pcap"],
        ["read", "captures/hrss_rtu.pcap", "--json"],
    ],
)
def test_read_on_rtu_input_is_byte_identical_forced_pure(args: list[str]) -> None:
    make_core()
    with_core = _mbmon(args, pure=False)
    pure = _mbmon(args, pure=True)
    assert with_core.returncode == pure.returncode == 0, with_core.stderr + pure.stderr
    assert with_core.stdout and with_core.stdout == pure.stdout
    assert with_core.stderr == pure.stderr


def test_read_on_a_generated_dump_is_byte_identical_forced_pure(tmp_path) -> None:
    make_core()
    dump = tmp_path / "bus.bin"
    dump.write_bytes(generated_bus(7, 400) + libmodbus_bus())
    for extra in ([], ["--json"]):
        args = ["read", "--rtu-raw", str(dump), *extra]
        with_core = _mbmon(args, pure=False)
        pure = _mbmon(args, pure=True)
        assert with_core.stdout and with_core.stdout == pure.stdout
        assert with_core.stderr == pure.stderr


def test_debug_core_says_which_decoder_frames_rtu() -> None:
    make_core()
    args = ["read", "--rtu-raw", "captures/sim_rtu.bin", "--debug-core"]
    fast = _mbmon(args, pure=False)
    assert b"core: the compiled core read the input (RTU framing, pairing and lines)" in (
        fast.stderr
    )
    # a dump has no capture times: --baud changes nothing there, the core reads it
    timed = _mbmon([*args, "--baud", "9600"], pure=False)
    assert b"core: the compiled core read the input (RTU framing" in timed.stderr
    # in a capture the timing rules are the reference decoder's
    port = ["read", "captures/sim_functions.pcap", "--rtu-port", "502", "--debug-core"]
    in_capture = _mbmon([*port, "--baud", "9600"], pure=False)
    assert b"RTU framing: the reference decoder (a baud rate" in in_capture.stderr
    profiled = _mbmon([*args, "--profile", "hrss"], pure=False)
    assert b"core: declined (--profile with --rtu-raw is not covered" in profiled.stderr
    assert b"core: RTU framing: the compiled framer (mbmon.core._rtu)" in profiled.stderr
    pure = _mbmon(args, pure=True)
    assert b"RTU framing: the reference decoder (the compiled RTU framer is unavailable" in (
        pure.stderr
    )
    assert fast.stdout == timed.stdout == pure.stdout
