"""``read``'s inputs on the core: several capture files in one run (each read as it is
alone, one record numbering, the run's stream ids as the reference's sources take
them) and gzip-compressed captures; core against forced pure, byte for byte (stdout
text and JSON, stderr, the exit status, and the ``-w`` log's messages)."""

from __future__ import annotations

import gzip
import tempfile
from pathlib import Path

import pytest
from core_diff import REAL, ROOT, require_core
from gen import T0, adus, every_function_pair, write_conversation, write_frames
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap_diff import log_contents
from opts_diff import assert_same, ran_core, read_run
from test_core_opts import _capture_and_options, _write_shape

from mbmon.io.pcap import TcpConversation
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request

OWN = sorted((ROOT / "captures").glob("*.pcap*"))
PUBLIC = sorted(REAL.glob("*.pcap*")) if REAL.is_dir() else []
DEMO = ROOT / "captures" / "demo.pcap"
HRSS = ROOT / "captures" / "hrss_ptp.pcap"
FUNCTIONS = ROOT / "captures" / "sim_functions.pcap"


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


def _gz(path: Path, into: Path) -> Path:
    out = into / (path.name + ".gz")
    out.write_bytes(gzip.compress(path.read_bytes()))
    return out


# ------------------------------------------------------------------ several inputs


@pytest.mark.parametrize(
    "args",
    [
        [DEMO, HRSS],
        [DEMO, DEMO, "--json"],
        [FUNCTIONS, DEMO, HRSS, "-t", "r"],
        [HRSS, DEMO, "-c", "40"],  # -c ends the run in the second input
        [FUNCTIONS, DEMO, "--fc", "4", "--since", "+1s", "-t", "r"],
        [DEMO, HRSS, "--robot", "127.0.0.1:502", "--json"],
        [DEMO, HRSS, "--profile", "hrss"],
        [DEMO, HRSS, "-q"],
    ],
    ids=str,
)
def test_several_own_captures(args: list[object]) -> None:
    assert_same(args, covered=True)  # type: ignore[arg-type]


def test_several_public_captures() -> None:
    """The public captures in threes (each one's neighbours), with several streams each."""
    if not PUBLIC:
        pytest.skip(f"{REAL} absent (../shared/captures/real)")
    for i in range(0, len(PUBLIC), 3):
        group = PUBLIC[i : i + 3]
        assert_same([*group, "--json" if i % 2 else "-t", *([] if i % 2 else ["e"])])


def test_one_declined_input_declines_the_run() -> None:
    run = assert_same([DEMO, ROOT / "captures" / "sim_rtu.pcap"], covered=False)
    assert run.core == ["core: declined (link type 147); the Python pipeline reads the input"]


def _mid_connection(path: Path, first: float, *, quiet_start: bool, unanswered: bool) -> Path:
    """Two connections caught mid-way (the same addresses in every file), each first
    seen in a bare ACK when ``quiet_start`` (streams made before the first item), then
    requests and answers; the last request unanswered when ``unanswered``."""
    pairs = every_function_pair()[:5]
    convs = [
        TcpConversation("10.0.0.1:40000", "10.0.0.2:502"),
        TcpConversation("10.0.0.3:40001", "10.0.0.2:502"),
    ]
    frames: list[bytes] = []
    for conv in convs:
        conv.client_next, conv.server_next = 1001, 5001
        if quiet_start:
            frames.append(conv.ack(True))
    for c, data in adus(pairs):
        frames += [conv.send(c, data) for conv in convs]
    if unanswered:
        frames.append(convs[1].send(True, encode_adu(99, 1, encode_read_request(3, 7, 2))))
    return write_frames(path, [(first + i * 0.01, f) for i, f in enumerate(frames)])


@pytest.mark.parametrize("quiet_start", [False, True])
def test_several_generated_inputs(tmp_path: Path, quiet_start: bool) -> None:
    """Stream ids as the reference's sources take them (each opened, its first item
    read, before any is read), the first input's requests timing out at its own end,
    the second's clock earlier than the first's, a third with a handshake."""
    a = _mid_connection(tmp_path / "a.pcap", T0 + 50.0, quiet_start=quiet_start, unanswered=True)
    b = _mid_connection(tmp_path / "b.pcap", T0, quiet_start=quiet_start, unanswered=False)
    c = write_conversation(tmp_path / "c.pcap", adus(every_function_pair()))
    for args in (
        [a, b, c],
        [c, a, b, "--json"],
        [a, b, "-c", "25"],
        [b, a, "--unit", "1", "-c", "9"],
    ):
        assert_same(args, covered=True)  # type: ignore[arg-type]
    text = read_run([a, b, "--json"]).out.decode()
    assert '"stream":3' in text and '"stream":4' not in text
    lines = read_run([a, b]).out.decode().splitlines()
    assert sum("No response" in line for line in lines) == 1


def test_several_inputs_into_one_log(tmp_path: Path) -> None:
    """``read A B -w x.mcap``: the same messages, schemas, channels and statistics."""
    a = _mid_connection(tmp_path / "a.pcap", T0 + 50.0, quiet_start=True, unanswered=True)
    for inputs in ([DEMO, HRSS], [a, DEMO, a]):
        for console in ([], ["-q"], ["--json"], ["-c", "80"], ["--fc", "16", "-c", "5", "-q"]):
            got, want = tmp_path / "core.mcap", tmp_path / "ref.mcap"
            fast = read_run([*inputs, *console, "-w", got])
            pure = read_run([*inputs, *console, "-w", want], pure=True)
            assert ran_core(fast), fast.core
            assert (fast.out, fast.err, fast.status) == (pure.out, pure.err, pure.status)
            got_c, want_c = log_contents(got), log_contents(want)
            for i, (x, y) in enumerate(zip(got_c["messages"], want_c["messages"], strict=False)):
                assert x == y, f"{inputs} {console}: message {i}"
            assert got_c == want_c


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(_capture_and_options(), min_size=2, max_size=3))
def test_drawn_inputs(drawn: list[tuple[dict[str, object], list[str]]]) -> None:
    """Two or three generated conversations in one run under the first one's options."""
    with tempfile.TemporaryDirectory() as tmp:
        paths = [
            _write_shape(Path(tmp) / f"in{i}.pcap", shape) for i, (shape, _) in enumerate(drawn)
        ]
        assert_same([*paths, *drawn[0][1]])


# ------------------------------------------------------------------ gzip


@pytest.mark.parametrize("path", OWN + PUBLIC[:6], ids=lambda p: p.name)
def test_gzip_captures(path: Path, tmp_path: Path) -> None:
    """A gzip-compressed capture reads as the capture itself (the core decompresses it
    into memory), and where the core covers the capture it covers the compressed one."""
    packed = _gz(path, tmp_path)
    plain = read_run([path])
    run = assert_same([packed])
    assert ran_core(run) == ran_core(plain)
    assert run.out == plain.out
    assert_same([packed, "--json", "-c", "10"])


def test_damaged_gzip_declines(tmp_path: Path) -> None:
    """A gzip stream cut short or not gzip at all past its magic: declined, and the
    reference's lines and its error (exit 1) either way."""
    packed = gzip.compress(FUNCTIONS.read_bytes())
    cut = tmp_path / "cut.pcap.gz"
    cut.write_bytes(packed[: len(packed) // 2])
    run = assert_same([cut], covered=False)
    assert run.status == 1 and "damaged gzip" in run.core[0]
    bad = tmp_path / "bad.pcap.gz"
    bad.write_bytes(b"\x1f\x8b" + bytes(200))
    assert_same([bad], covered=False)
    assert_same([DEMO, cut], covered=False)
