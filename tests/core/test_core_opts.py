"""``read``'s view options on the core: every ``-t`` mode and ``--robot`` labels, core
against forced pure, byte for byte (stdout text and JSON, stderr's summary and
warnings, the exit status), on the captures and on generated ones."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from core_diff import REAL, ROOT, require_core
from gen import T0, adus, every_function_pair, write_conversation, write_frames
from opts_diff import assert_same, read_run

from mbmon.io.pcap import TcpConversation

OWN = sorted((ROOT / "captures").glob("*.pcap*"))
PUBLIC = sorted(REAL.glob("*.pcap*")) if REAL.is_dir() else []
MODES = ("r", "ad", "e", "u", "ud")
DEMO = ROOT / "captures" / "demo.pcap"


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


def _ends(path: Path) -> tuple[str, str] | None:
    """The client and server endpoints of the first frame of a capture, or None."""
    first = read_run([path, "--json", "-c", "1", "-q"], pure=True)
    lines = [json.loads(line) for line in first.out.splitlines()]
    run = read_run([path, "--json", "-c", "1"], pure=True)
    for obj in [*lines, *(json.loads(line) for line in run.out.splitlines())]:
        if obj.get("kind") == "request":
            return obj["src"], obj["dst"]
        if obj.get("kind") in ("response", "exception"):
            return obj["dst"], obj["src"]
    return None


@pytest.mark.parametrize("path", OWN + PUBLIC, ids=lambda p: p.name)
def test_time_modes_and_robot_on_captures(path: Path) -> None:
    """Each capture in two ``-t`` modes (text, JSON) and with the robot as the server
    (by host), by its endpoint with a JSON line, and as the client."""
    i = (OWN + PUBLIC).index(path)
    assert_same([path, "-t", MODES[i % 5]])
    assert_same([path, "-t", MODES[(i + 2) % 5], "--json"])
    ends = _ends(path)
    if ends is None:
        return
    client, server = ends
    assert_same([path, "--robot", server.rsplit(":", 1)[0]])
    assert_same([path, "--robot", server, "--json", "-t", "r"])
    assert_same([path, "--robot", client.rsplit(":", 1)[0], "-t", MODES[(i + 4) % 5]])


def test_the_core_covers_them() -> None:
    """The view options no longer keep a covered capture off the core."""
    for args in (["-t", "r"], ["-t", "ud", "--json"], ["--robot", "127.0.0.1:502"]):
        assert_same([DEMO, *args], covered=True)


@pytest.mark.parametrize("mode", ("a", *MODES))
def test_days_long_and_impossible_times(tmp_path: Path, mode: str) -> None:
    """A capture spanning days (the automatic date of a and u), times backwards, the
    epoch, and the last second pcap holds, in every mode."""
    stream = adus(every_function_pair()[:8])
    times = [T0 + 86400 * 2.5 * i for i in range(len(stream) + 7)]
    times[5] = T0 - 3600.0  # backwards
    times[9] = 0.0  # the epoch
    times[12] = 4294967295.999999  # the last second pcap holds
    path = write_conversation(tmp_path / "days.pcap", stream, times=times)
    for fmt in ([], ["--json"]):
        assert_same([path, "-t", mode, *fmt], covered=True)


def _two_clients(path: Path) -> Path:
    """Two clients of one server, then a second server of the first client: the robot's
    labels name the peer from the second one on."""
    pairs = every_function_pair()[:6]
    convs = [
        TcpConversation("10.0.0.1:40000", "10.0.0.2:502"),
        TcpConversation("10.0.0.3:40001", "10.0.0.2:502"),
        TcpConversation("10.0.0.1:40002", "10.0.0.9:502"),
    ]
    frames: list[bytes] = list(convs[0].open())
    for c, data in adus(pairs[:2]):
        frames.append(convs[0].send(c, data))
    frames += convs[1].open()
    frames += convs[2].open()
    for c, data in adus(pairs):
        frames += [conv.send(c, data) for conv in convs]
    for conv in convs:
        frames += conv.close(True)
    return write_frames(path, [(T0 + i * 0.01, f) for i, f in enumerate(frames)])


@pytest.mark.parametrize(
    "robot", ["10.0.0.2", "10.0.0.2:502", "10.0.0.1", "10.0.0.1:40002", "10.0.0.7", "[10.0.0.2]"]
)
def test_robot_labels_with_several_peers(tmp_path: Path, robot: str) -> None:
    """The robot as server of two clients, as client of two servers, on one stream of
    several, and absent (the warning): lines, JSON lines, events and the summary."""
    path = _two_clients(tmp_path / "peers.pcap")
    for fmt in ([], ["--json"]):
        run = assert_same([path, "--robot", robot, *fmt], covered=True)
    if robot == "10.0.0.7":
        assert "appears in no stream" in run.err
    elif robot == "10.0.0.2":
        text = read_run([path, "--robot", robot]).out.decode()
        assert "Receive from client  [" in text and "Receive from client 10.0.0.3:40001" in text
