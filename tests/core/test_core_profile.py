"""``read --profile`` on the compiled core against the reference pipeline, byte for byte.

The core writes the notes of read requests and their answers from the profile's
compiled register map and hands the rest (writes, exceptions, what it does not
compile) to the annotator; a device session sees only what its ``CoreWatch``
asks for. These suites hold both paths equal, text and JSON and the summary
(robot commands and warnings included): on the project's HRSS captures, a
small realistic HRSS cell (bench/realistic.py's generator), a generated HRSS
session with commands that succeed, fail, are rejected and never complete, and
a data-only profile with every register kind at the edges of its values.
"""

from __future__ import annotations

import random
import struct
import subprocess
import sys
from pathlib import Path

import core_diff
import pytest
from core_diff import REAL, ROOT, require_core

from mbmon.io.pcap import PcapWriter, TcpConversation
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import (
    encode_exception,
    encode_read_request,
    encode_read_response,
    encode_write_multiple_request,
    encode_write_multiple_response,
    encode_write_single,
)

T0 = 1_700_000_000.125
HERE = Path(__file__).resolve().parent


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


# --------------------------------------------------------------------------- the harness


def reference(path: Path, specs: list[str], *, as_json: bool, timeout: float) -> tuple[bytes, str]:
    """``mbmon read --profile ...`` by the Python pipeline: stdout's bytes, the summary."""
    return core_diff.reference(path, as_json=as_json, timeout=timeout, specs=specs)


def with_core(
    path: Path, specs: list[str], *, as_json: bool, timeout: float
) -> tuple[bytes, str, str | None]:
    """The same by the core: stdout's bytes, the summary, why it declined (or None)."""
    return core_diff.with_core(path, as_json=as_json, timeout=timeout, specs=specs)


def assert_same(path: Path, specs: list[str], *, timeout: float = 1.0) -> bytes:
    """Core and reference agree byte for byte, text and JSON, and in the summary; the
    core must run. Returns the text output."""
    text = b""
    for as_json in (False, True):
        got, got_summary, why = with_core(path, specs, as_json=as_json, timeout=timeout)
        assert why is None, f"the core declined {path.name}: {why}"
        want, want_summary = reference(path, specs, as_json=as_json, timeout=timeout)
        got_lines, want_lines = got.splitlines(), want.splitlines()
        for i, (a, b) in enumerate(zip(got_lines, want_lines, strict=False)):
            assert a == b, f"{path.name} json={as_json} line {i}"
        assert len(got_lines) == len(want_lines), f"{path.name} json={as_json}: line count"
        assert got == want
        assert got_summary == want_summary
        if not as_json:
            text = got
    return text


# --------------------------------------------------------------------------- captures


def write_capture(path: Path, steps: list[tuple[float, int, int, bytes | None, bytes | None]]):
    """Connections to 10.0.0.2:502 (one per client number), each step ``(time, client,
    unit, request PDU or None, answer PDU or None)``: the request at ``time``, its answer
    2 ms later, transaction ids counting per client."""
    convs: dict[int, TcpConversation] = {}
    tids: dict[int, int] = {}
    frames: list[tuple[float, bytes]] = []
    for t, client, unit, req, resp in steps:
        conv = convs.get(client)
        if conv is None:
            conv = convs[client] = TcpConversation(f"10.0.0.{10 + client}:4{client:04d}",
                                                   "10.0.0.2:502")  # fmt: skip
            frames += [(T0 + t - 0.001, f) for f in conv.open()]
        tid = tids[client] = (tids.get(client, 0) + 1) & 0xFFFF
        if req is not None:
            frames.append((T0 + t, conv.send(True, encode_adu(tid, unit, req))))
        if resp is not None:
            frames.append((T0 + t + 0.002, conv.send(False, encode_adu(tid, unit, resp))))
    end = max(ts for ts, _ in frames) + 0.5
    for conv in convs.values():
        frames += [(end, f) for f in conv.close(True)]
    with PcapWriter(path) as w:
        for ts, frame in sorted(frames, key=lambda x: x[0]):
            w.write(ts, frame)
    return path


def words32(value: int) -> list[int]:
    value &= 0xFFFFFFFF
    return [value & 0xFFFF, value >> 16]


def rd(fc: int, address: int, values: list[int]) -> tuple[bytes, bytes]:
    """A read request and its answer."""
    return encode_read_request(fc, address, len(values)), encode_read_response(fc, values)


class Cell:
    """An HRSS cell's steps, written in the order a PLC would make them."""

    def __init__(self, client: int = 0, unit: int = 1) -> None:
        self.t = 0.0
        self.client = client
        self.unit = unit
        self.steps: list[tuple[float, int, int, bytes | None, bytes | None]] = []

    def step(self, req: bytes | None, resp: bytes | None, dt: float = 0.01) -> None:
        self.t += dt
        self.steps.append((self.t, self.client, self.unit, req, resp))

    def read(self, fc: int, address: int, values: list[int], dt: float = 0.01) -> None:
        self.step(*rd(fc, address, values), dt=dt)

    def poll(self, motion: int, status: int, action: int = 0, queue: int = 3) -> None:
        k = len(self.steps)
        joints = [w for j in range(12) for w in words32(int(90000 * ((k + j) % 7 - 3)))]
        self.read(4, 500, joints)
        self.read(4, 524, [motion & 0xFFFF])
        self.read(4, 200, [status & 0xFFFF, action & 0xFFFF])
        self.read(4, 102, [queue & 0xFFFF])

    def write(self, address: int, values: list[int], answer: str = "ok") -> None:
        values = [v & 0xFFFF for v in values]
        if len(values) == 1 and address == 200:
            req = encode_write_single(6, address, values[0])
            resp: bytes | None = req
            fc = 6
        else:
            req = encode_write_multiple_request(16, address, values)
            resp = encode_write_multiple_response(16, address, len(values))
            fc = 16
        if answer == "exception":
            resp = encode_exception(fc, 4)
        elif answer == "none":
            resp = None
        self.step(req, resp)

    def command(self, values: list[int], answer: str = "ok") -> None:
        self.write(201, values)
        self.write(200, [1], answer)


PTP = [0, 0, 0, 0, 0, *words32(90000), *([0] * 10), 50, 100, 1, 2]
LIN = [1, 1, 1, *words32(300000), *words32(-20000), *words32(400000), *([0] * 6), 200, 100]
JOG = [3, 0, 1]
GET_PR = [200, 5]


def hrss_session_steps() -> list[tuple[float, int, int, bytes | None, bytes | None]]:
    """Commands that succeed, fail, are rejected, never complete and return values, with
    the motion, status and queue registers the session watches, on two units and two
    connections to the same robot."""
    a = Cell()
    a.poll(1, 0)
    a.command(PTP)  # succeeds while moving, then the motion ends
    a.poll(2, 0)
    a.poll(2, 1, 0)
    a.poll(2, 1, 0)
    a.poll(1, 1, 0)
    a.write(200, [0])
    a.command(LIN)  # fails
    a.poll(1, 0, 1)
    a.poll(1, 2, 1)
    a.write(200, [0])
    a.command(PTP, answer="exception")  # the execute is rejected
    a.poll(1, 0)
    a.command(LIN)  # executed without a reset
    a.poll(3, 0, 1, queue=8001)  # queue over its limit, hold
    a.poll(3, 0, 1, queue=8001)
    a.poll(4, 0, 1, queue=12)
    for _ in range(13):  # never completes: no status for more than 10 s
        a.poll(4, 0, 1)
        a.t += 0.9
    a.write(200, [0])
    a.command(JOG)  # hold to run, stopped by R200 = 0
    a.poll(2, 0, 3)
    a.write(200, [0])
    a.poll(1, 1, 3)
    a.command(GET_PR)  # a Get command: returns read from IR202..
    a.read(4, 200, [1, 200, 5, 1, *words32(12345), *words32(-5), *([0] * 8)])
    a.read(4, 200, [1, 200, 5, 1, *words32(12346), *words32(-5), *([0] * 8)])
    a.read(3, 200, [1, 200, 5] + [0] * 10)  # the holding image, as read back
    a.command(PTP)  # R200 still 1: executed without a reset
    a.poll(1, 1, 0)
    a.write(200, [0])
    a.write(201, PTP, answer="none")  # a write nobody answers: times out
    a.t += 2.0
    a.poll(1, 0)
    a.step(None, encode_read_response(4, [7]))  # an answer nothing asked for
    a.read(4, 500, [0x8000, 0xFFFF, 0x7FFF, 0x8000] + [0xFFFF] * 20)  # edge values
    a.step(encode_read_request(4, 524, 1), encode_exception(4, 2))  # an exception to a read
    a.step(encode_read_request(4, 200, 2), b"\x04\x03\x00\x01\x00")  # a byte count it breaks
    b = Cell(client=1)  # a second connection to the same robot and unit: the same session
    b.t = a.t + 1.0
    b.command(PTP)
    a.t = b.t + 0.005
    a.poll(2, 1, 0)  # the status the first connection reads is of the second's command
    c = Cell(client=1, unit=2)  # another unit: a session of its own
    c.t = a.t + 0.5
    c.poll(1, 0)
    c.command(LIN)
    c.poll(1, 1, 1)
    return sorted(a.steps + b.steps + c.steps, key=lambda s: s[0])


# --------------------------------------------------------------------------- HRSS


def test_hrss_session_commands(tmp_path: Path) -> None:
    """Every kind of command lifecycle the session reports, identical on both paths."""
    path = write_capture(tmp_path / "hrss.pcap", hrss_session_steps())
    text = assert_same(path, ["hrss"])
    expected = [
        b"[success after", b"[fail after", b"execute rejected", b"never completed",
        b"execute without reset", b"motion done", b"commands queued", b"[returned]",
        b"stop: JOG", b"motion: Idle (1) -> Running (2)", b"-- No response to",
    ]  # fmt: skip
    for what in expected:
        assert what in text, what


def test_hrss_timeout_and_bindings(tmp_path: Path) -> None:
    """The same with a short pairing timeout and per-unit and per-server bindings."""
    path = write_capture(tmp_path / "hrss.pcap", hrss_session_steps())
    assert_same(path, ["hrss"], timeout=0.001)
    assert_same(path, ["unit:1=hrss"])
    assert_same(path, ["10.0.0.2:502=hrss", "unit:2=xeg"])


def test_hrss_writes_beyond_the_session_memory(tmp_path: Path) -> None:
    """300 writes in flight before their answers: the session forgets the oldest (a
    warning), so their answers go through the annotator again (``core_write_answer``
    says None); the others are confirmed by the core's narrow call."""
    cell = Cell()
    requests = []
    for i in range(300):  # R200 = 0 (a reset), whose echo the core notes itself
        req = encode_write_single(6, 200, 0) if i % 3 else encode_write_single(6, 203, i)
        requests.append(req)
        cell.step(req, None, dt=0.001)
    for i, req in enumerate(requests):  # the answers, in order, same transaction ids
        cell.steps.append((cell.t + 0.001 * (i + 1), 0, 1, None, req))
    steps = [(t, c, u, q, r) for t, c, u, q, r in cell.steps]
    # answers carry the request's transaction id: write them as one conversation
    path = tmp_path / "many.pcap"
    conv = TcpConversation("10.0.0.10:40000", "10.0.0.2:502")
    with PcapWriter(path) as w:
        for frame in conv.open():
            w.write(T0, frame)
        for tid, (t, _, unit, req, _) in enumerate(steps[:300], 1):
            w.write(T0 + t, conv.send(True, encode_adu(tid, unit, req or b"")))
        for tid, (t, _, unit, _, resp) in enumerate(steps[300:], 1):
            w.write(T0 + t, conv.send(False, encode_adu(tid, unit, resp or b"")))
    text = assert_same(path, ["hrss"], timeout=100.0)
    assert b"writes unanswered" in text


def test_hrss_realistic_cell(tmp_path: Path) -> None:
    """bench/realistic.py's HRSS cell (state polled every cycle, commands every 25)."""
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import realistic
    finally:
        sys.path.remove(str(ROOT / "bench"))
    path = tmp_path / "cell.pcap"
    realistic.build(path, realistic.hrss_adus(random.Random(10), 3000), 1, 1, "aligned", seed=10)
    text = assert_same(path, ["hrss"])
    assert b"[success after" in text and b"motion:" in text


@pytest.mark.parametrize("name", ["hrss_ptp.pcap", "demo.pcap", "sim_functions.pcap",
                                  "sim_exceptions.pcap"])  # fmt: skip
def test_own_captures(name: str) -> None:
    assert_same(ROOT / "captures" / name, ["hrss"])


def test_public_captures() -> None:
    """The real captures others made, under the HRSS profile (where the core covers them)."""
    public = sorted(REAL.glob("tcp__*.pcap*")) if REAL.is_dir() else []
    if not public:
        pytest.skip(f"{REAL} absent (../shared/captures/real)")
    ran = 0
    for path in public:
        for as_json in (False, True):
            got, got_summary, why = with_core(path, ["hrss"], as_json=as_json, timeout=1.0)
            if why is not None:
                continue
            ran += 1
            want, want_summary = reference(path, ["hrss"], as_json=as_json, timeout=1.0)
            assert got == want, path.name
            assert got_summary == want_summary, path.name
    assert ran >= len(public) // 2


# --------------------------------------------------------------------------- every kind

KINDS = """\
[profile]
name = "kinds"
description = "every register kind (tests of the compiled core)"

[[holding_registers]]
name = "U"
address = 0
type = "u16"
unit = "rpm"

[[holding_registers]]
name = "S"
address = 1
type = "s16"
scale = 0.1
unit = "°C"
range = [-400, 1500]

[[holding_registers]]
name = "L"
address = 2
type = "i32"
scale = 0.001
unit = "mm"

[[holding_registers]]
name = "UL"
address = 4
type = "u32"
display = "hex"

[[holding_registers]]
name = "F"
address = 6
type = "f32"
unit = "bar"

[[holding_registers]]
name = "FS"
address = 8
type = "f32"
scale = 2.5
word_order = "high_low"

[[holding_registers]]
name = "Q"
address = 10
type = "s16"
scale = 0.25
unit = "%"

[[holding_registers]]
name = "E"
address = 11
type = "u16"
range = [0, 1]
enum = { 0 = "off", 1 = "on" }

[[holding_registers]]
name = "EV"
address = 12
type = "s16"
enum_style = "value"
enum = { "-1" = "negative", 1 = "one" }

[[holding_registers]]
name = "H"
address = 13
type = "s16"
display = "hex"

[[holding_registers]]
name = "SR[{n}]"
address = 14
n = [1, 16]
type = "s16"

[[holding_registers]]
name = "HL"
address = 30
type = "i32"
word_order = "high_low"
scale = 0.01
label = "swapped"

[[holding_registers]]
name = "UU"
address = 32
type = "u32"
range = [0, 100000]

[[holding_registers]]
name = "V"
address = 34
type = "version"
words = 2
format = "V{0}.{1}"

[[holding_registers]]
name = "B"
address = 36
type = "block"
words = 3
label = "params"

[[holding_registers]]
name = "PR[{n}]"
address = 40
n = [1, 3]
stride = 3
select = "type"

[[holding_registers.fields]]
name = "type"
offset = 0
enum = { 0 = "NULL", 1 = "Joint", 2 = "Cartesian" }

[[holding_registers.fields]]
name = "Value1"
offset = 1
type = "i32"
scale = 0.001
variants = { 1 = { name = "A1", unit = "°" }, 2 = { name = "X", unit = "mm" } }

[[holding_registers]]
name = "UR[{n}]"
address = 50
n = [1, 4]
type = "u16"

[[holding_registers]]
name = "HIGH"
address = 40001
type = "u16"
label = "a holding register far up"

[[input_registers]]
name = "IHIGH"
address = 40001
type = "s16"
label = "an input register at the same address"

[[input_registers]]
name = "T"
address = 0
type = "u16"
label = "temperature"
scale = 0.01
unit = "%"

[[input_registers]]
name = "W"
address = 1
type = "s16"
scale = 0.5
label = "half \\"steps\\""

[[coils]]
name = "DO[{n}]"
address = 0
n = [1, 16]

[[discrete_inputs]]
name = "DI[{n}]"
address = 0
n = [1, 16]
labels = { 1 = "Start" }
"""

EDGES = [0, 1, 0x7FFF, 0x8000, 0xFFFF, 0xFFFE, 0x7F80, 0xFF80, 0x7FC0, 0xFFC0, 0x3F80, 0x7F7F,
         0x0001, 0x0080, 399, 400, 1500, 1501, 0xFE70, 0xFE6F]  # fmt: skip
FLOATS = [0.0, -0.0, 1.0, -1.5, 1e-45, 3.4e38, 1e16, 123456.789, 1e-5, 0.1, float("inf"),
          float("-inf"), float("nan")]  # fmt: skip


def _f32_words(x: float, high_low: bool) -> list[int]:
    u = struct.unpack(">I", struct.pack(">f", x))[0]
    low, high = u & 0xFFFF, u >> 16
    return [high, low] if high_low else [low, high]


def kinds_steps(seed: int) -> list[tuple[float, int, int, bytes | None, bytes | None]]:
    """Reads over every kind (and across their edges), writes, bits; values at the edges."""
    rng = random.Random(seed)
    cell = Cell()
    shapes = [(3, 0, 14), (3, 0, 40), (3, 2, 3), (3, 3, 4), (3, 14, 16), (3, 14, 12),
              (3, 30, 4), (3, 34, 6), (3, 40, 9), (3, 41, 2), (3, 50, 4), (3, 5, 30),
              (4, 0, 2), (4, 0, 1), (4, 1, 5), (3, 100, 5), (3, 0, 125),
              (3, 40000, 3), (4, 40000, 3), (3, 65530, 6), (4, 65535, 1)]  # fmt: skip
    for _ in range(400):
        fc, address, count = rng.choice(shapes)
        values = [rng.choice(EDGES) if rng.random() < 0.5 else rng.randrange(65536)
                  for _ in range(count)]  # fmt: skip
        if fc == 3 and address <= 6 < address + count - 1 and rng.random() < 0.5:
            values[6 - address : 8 - address] = _f32_words(rng.choice(FLOATS), False)
        if fc == 3 and address <= 8 < address + count - 1 and rng.random() < 0.5:
            values[8 - address : 10 - address] = _f32_words(rng.choice(FLOATS), True)
        cell.read(fc, address, values)
    for fc, count in ((1, 16), (2, 16), (1, 9), (2, 3)):
        bits = [rng.randrange(2) for _ in range(count)]
        cell.step(encode_read_request(fc, 0, count), encode_read_response(fc, bits, count))
    cell.write(0, [rng.randrange(65536) for _ in range(20)])
    cell.step(encode_write_single(6, 11, 7), encode_write_single(6, 11, 7))
    cell.step(encode_write_single(5, 3, 0xFF00), encode_write_single(5, 3, 0xFF00))
    cell.step(encode_read_request(3, 0, 4), encode_exception(3, 2))
    return cell.steps


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_every_register_kind(tmp_path: Path, seed: int) -> None:
    """A data-only profile with every type, format, scale, enum, range, run and the kinds
    the core leaves to the annotator (version, block, selector groups, cut values, bits)."""
    profile = tmp_path / "kinds.toml"
    profile.write_text(KINDS, encoding="utf-8")
    path = write_capture(tmp_path / "kinds.pcap", kinds_steps(seed))
    text = assert_same(path, [str(profile)])
    for what in ("nan", "inf", "(out of range -400..1500)", "(unknown)", "… (+", "-1 (negative)",
                 "0xFFFFFFFF", "V", "PR[", '"steps"', "IHIGH an input"):  # fmt: skip
        assert what.encode() in text, what


# --------------------------------------------------------------------------- declines


def test_a_session_without_core_support_is_declined(tmp_path: Path) -> None:
    """The toy pump's session (tests/semantics/toy_pump.py) does not support the core:
    the profile is declined before a byte is written; its data-only twin runs."""
    sys.path.insert(0, str(HERE.parent / "semantics"))
    try:
        from toy_pump import DATA_ONLY, PROFILE, ToyPumpSession
    finally:
        sys.path.remove(str(HERE.parent / "semantics"))
    from mbmon.semantics.session import register_session, unregister_session

    register_session("toy_pump", ToyPumpSession)
    try:
        pump = tmp_path / "pump.toml"
        pump.write_text(PROFILE, encoding="utf-8")
        path = write_capture(tmp_path / "pump.pcap", [
            (0.01, 0, 1, *rd(3, 0, [250, 1])),
            (0.02, 0, 1, *rd(4, 0, [250])),
        ])  # fmt: skip
        got, _, why = with_core(path, [str(pump)], as_json=False, timeout=1.0)
        assert got == b"" and why is not None and "toy_pump" in why
        data = tmp_path / "map.toml"
        data.write_text(DATA_ONLY, encoding="utf-8")
        assert b"setpoint = 250 ml" in assert_same(path, [str(data)])
    finally:
        unregister_session("toy_pump")


def test_cli_runs_profiles_on_the_core(tmp_path: Path) -> None:
    """``mbmon read --profile hrss --debug-core``: the core ran, the same bytes as with
    ``MBMON_NO_EXTENSIONS=1``; with ``-w`` the profile is declined (the log's state)."""
    path = write_capture(tmp_path / "hrss.pcap", hrss_session_steps())

    def read(*extra: str, pure: bool = False) -> subprocess.CompletedProcess[bytes]:
        env = dict(__import__("os").environ)
        if pure:
            env["MBMON_NO_EXTENSIONS"] = "1"
        return subprocess.run(
            [sys.executable, "-m", "mbmon", "read", str(path), "--profile", "hrss", *extra],
            capture_output=True, timeout=300, cwd=ROOT, env=env, check=False,
        )  # fmt: skip

    done = read("--debug-core")
    assert done.returncode == 0, done.stderr
    assert b"core: the compiled core read the input" in done.stderr
    pure = read(pure=True)
    assert done.stdout == pure.stdout
    assert done.stderr.split(b"\n", 1)[1] == pure.stderr
    logged = read("--debug-core", "-w", str(tmp_path / "x.jsonl"))
    assert b"core: declined" in logged.stderr
