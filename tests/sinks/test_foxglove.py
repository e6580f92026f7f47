"""The live Foxglove feed: a real foxglove-sdk server and a real WebSocket client.

The client speaks Foxglove's WebSocket protocol (foxglove-sdk 0.30 offers the
subprotocol ``foxglove.sdk.v1``; older Foxglove and Lichtblick releases offer
only ``foxglove.websocket.v1``, the same protocol, and connect too): it reads
``serverInfo`` and ``advertise``, subscribes, and decodes the binary
message-data frames (opcode 0x01, subscription id u32 LE, log time u64 LE,
payload). What it receives is checked
against the schemas in ``mbmon/schemas`` and against the MCAP log of the same
records, byte for byte: the feed and the log are one mapping.
"""

from __future__ import annotations

import base64
import json
import os
import re
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("foxglove", reason="foxglove-sdk not installed (pip install 'mbmon[foxglove]')")
pytest.importorskip("websockets", reason="websockets not installed (the test extra)")

import argparse

import jsonschema
from format4 import as_format3
from sink_records import REPO, hrss_context
from websockets.sync.client import connect

from mbmon.commands.common import FOXGLOVE_DEFAULT, foxglove_address
from mbmon.io.mcap.layout import PROTO_TOPICS, TOPIC_SCHEMAS, schema_text, topics
from mbmon.io.mcap.proto import decode_payload, descriptor_set
from mbmon.io.mcap.reader import McapLog
from mbmon.model import Chunk, Record
from mbmon.sinks.base import SinkContext, SinkError, open_sink
from mbmon.sinks.foxglove import FoxgloveFeed

SUBPROTOCOL = "foxglove.sdk.v1"
LEGACY = "foxglove.websocket.v1"
_DATA = struct.Struct("<BIQ")  # opcode 0x01, subscription id, log time


class Client:
    """A Foxglove WebSocket client: advertised channels, subscriptions, received messages
    (``(topic, log_time, payload)``), read by a thread while the test feeds the server."""

    def __init__(self, url: str, subprotocols: tuple[str, ...] = (SUBPROTOCOL,)) -> None:
        self.ws = connect(url, subprotocols=list(subprotocols), open_timeout=10).__enter__()
        self.server_info: dict[str, Any] = {}
        self.channels: dict[str, dict[str, Any]] = {}  # topic -> advertised channel
        self.received: list[tuple[str, int, bytes]] = []
        self._subs: dict[int, str] = {}
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self.closed = threading.Event()

    def read_advertised(self, wanted: set[str], timeout: float = 10.0) -> None:
        end = time.monotonic() + timeout
        while not wanted <= set(self.channels):
            left = end - time.monotonic()
            assert left > 0, f"not advertised: {wanted - set(self.channels)}"
            self._control(self.ws.recv(timeout=left))

    def _control(self, message: str | bytes) -> None:
        assert isinstance(message, str), "no data before a subscription"
        obj = json.loads(message)
        if obj["op"] == "serverInfo":
            self.server_info = obj
        elif obj["op"] == "advertise":
            for ch in obj["channels"]:
                self.channels[ch["topic"]] = ch

    def subscribe(self, wanted: list[str]) -> None:
        subs = []
        for n, topic in enumerate(wanted, 1):
            self._subs[n] = topic
            subs.append({"id": n, "channelId": self.channels[topic]["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        try:
            for message in self.ws:
                if isinstance(message, bytes):
                    opcode, sub, log_time = _DATA.unpack_from(message)
                    assert opcode == 0x01
                    with self._lock:
                        self.received.append((self._subs[sub], log_time, message[_DATA.size :]))
                else:
                    self._control(message)
        except Exception:
            pass
        finally:
            self.closed.set()

    def messages(self) -> list[tuple[str, int, bytes]]:
        with self._lock:
            return list(self.received)

    def wait_for(self, count: int, timeout: float = 10.0) -> list[tuple[str, int, bytes]]:
        end = time.monotonic() + timeout
        while len(self.messages()) < count and time.monotonic() < end:
            time.sleep(0.02)
        return self.messages()

    def close(self) -> None:
        self.ws.close()


def _log_messages(path: Path, wanted: set[str]) -> list[tuple[str, int, bytes]]:
    """The messages of an MCAP log on ``wanted`` topics, without the writer's stats events."""
    out = []
    with McapLog(path) as log:
        for msg in log.messages(wanted):
            if msg.topic == "/mbmon/events" and json.loads(msg.raw).get("index") is None:
                continue
            out.append((msg.topic, msg.log_time, msg.raw))
    return out


def _validators() -> dict[str, Any]:
    out = {}
    for topic, name in TOPIC_SCHEMAS.items():
        schema = json.loads(schema_text(name))
        cls = jsonschema.validators.validator_for(schema, default=jsonschema.Draft202012Validator)
        out[topic] = cls(schema)
    return out


def _feed_like_the_hub(listener: Any, stream: list[Chunk | Record]) -> None:
    """Chunks one by one, records in the batches the hub makes between chunks."""
    batch: list[Record] = []
    for item in stream:
        if isinstance(item, Chunk):
            if batch:
                listener.on_records(batch)
                batch = []
            listener.on_chunk(item)
        else:
            batch.append(item)
    if batch:
        listener.on_records(batch)


def _decoded(topic: str, payload: bytes) -> Any:
    """A served message's object: format 3's protobuf topics decoded, the rest JSON."""
    if topic in PROTO_TOPICS:
        return decode_payload(PROTO_TOPICS[topic], "protobuf", payload)
    return json.loads(payload)


def _wait_subscribed(feed: FoxgloveFeed, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while not feed.subscribed():
        assert time.monotonic() < end, "the subscription never reached the server"
        time.sleep(0.02)


# --------------------------------------------------------------------------- in process


def test_feed_serves_the_logs_topics_schemas_and_messages(
    tmp_path: Path, hrss_stream: list
) -> None:
    ctx = hrss_context(robot="127.0.0.1:502")
    log = tmp_path / "same.mcap"
    with open_sink(log, ctx) as sink:
        _feed_like_the_hub(sink, hrss_stream)
    feed = FoxgloveFeed(ctx, "127.0.0.1", 0)
    try:
        assert feed.port > 0 and feed.url == f"ws://127.0.0.1:{feed.port}"
        client = Client(feed.url)
        every = set(topics(True))
        client.read_advertised(every)
        assert set(client.channels) == every  # the log's channels, no more
        for topic, ch in client.channels.items():
            if topic in PROTO_TOPICS:  # log format 3: protobuf, its FileDescriptorSet base64
                assert ch["encoding"] == ch["schemaEncoding"] == "protobuf"
                assert ch["schemaName"] == PROTO_TOPICS[topic]
                assert base64.b64decode(ch["schema"]) == descriptor_set()
                continue
            assert ch["encoding"] == "json"
            assert ch["schemaEncoding"] == "jsonschema"
            assert ch["schemaName"] == TOPIC_SCHEMAS[topic]
            assert ch["schema"].encode() == schema_text(TOPIC_SCHEMAS[topic])
        assert client.channels["/modbus/monitor"]["schemaName"] == "foxglove.Log"
        client.subscribe(sorted(every))
        _wait_subscribed(feed)
        _feed_like_the_hub(feed, hrss_stream)
        expected = as_format3(_log_messages(log, every))  # a feed serves every chunk
        got = client.wait_for(len(expected))
        client.close()
    finally:
        feed.close()
    assert len(got) == len(expected) == feed.messages_sent
    assert got == expected  # same topics, log times and JSON bytes, in the same order
    validators = _validators()
    for topic, _log_time, payload in got:
        validators[topic].validate(_decoded(topic, payload))
    seen = {topic for topic, _, _ in got}
    assert {"/modbus/monitor", "/hrss/state", "/hrss/commands", "/modbus/raw"} <= seen
    # a Plot panel on /hrss/state.a1 has numbers to draw
    states = [json.loads(p) for t, _, p in got if t == "/hrss/state"]
    assert any(isinstance(s.get("a1"), float | int) for s in states)


def test_only_subscribed_topics_are_made_and_sent(session_stream: list) -> None:
    ctx = SinkContext(source="x.pcap")  # no profile: no /hrss channels
    feed = FoxgloveFeed(ctx, "127.0.0.1", 0)
    try:
        assert feed.topics == topics(False)
        _feed_like_the_hub(feed, session_stream)
        assert feed.messages_sent == 0  # nobody listens: nothing made, nothing queued
        client = Client(feed.url)
        client.read_advertised({"/modbus/monitor"})
        assert "/hrss/state" not in client.channels
        client.subscribe(["/modbus/monitor"])
        _wait_subscribed(feed)
        _feed_like_the_hub(feed, session_stream)
        records = [r for r in session_stream if isinstance(r, Record)]
        got = client.wait_for(len(records))
        client.close()
    finally:
        feed.close()
    assert [t for t, _, _ in got] == ["/modbus/monitor"] * len(records)
    assert [json.loads(p)["line"] for _, _, p in got] == [r.index for r in records]


@pytest.mark.parametrize(
    ("offered", "agreed"),
    [
        ((LEGACY,), LEGACY),  # older Foxglove and Lichtblick releases
        ((LEGACY, SUBPROTOCOL), SUBPROTOCOL),
        ((SUBPROTOCOL,), SUBPROTOCOL),
    ],
)
def test_clients_offering_either_subprotocol_get_the_same_messages(
    session_stream: list, offered: tuple[str, ...], agreed: str
) -> None:
    """A client that offers only ``foxglove.websocket.v1`` (refused with HTTP 400 by the
    SDK's server alone) connects, subscribes and receives what a current client does."""
    feed = FoxgloveFeed(SinkContext(source="x.pcap"), "127.0.0.1", 0)
    try:
        clients = [Client(feed.url, offered), Client(feed.url)]
        assert clients[0].ws.subprotocol == agreed
        for client in clients:
            client.read_advertised({"/modbus/monitor"})
            assert client.server_info["name"] == "mbmon"
            client.subscribe(["/modbus/monitor"])
        records = [r for r in session_stream if isinstance(r, Record)]
        end = time.monotonic() + 10
        while not all(client.messages() for client in clients):  # both subscriptions in
            assert time.monotonic() < end, "a subscription never reached the server"
            feed.on_records(records[:1])
            time.sleep(0.05)
        time.sleep(0.2)
        before = [len(client.messages()) for client in clients]
        _feed_like_the_hub(feed, session_stream)
        got = [
            client.wait_for(n + len(records))[n:] for client, n in zip(clients, before, strict=True)
        ]
        for client in clients:
            client.close()
    finally:
        feed.close()
    assert len(got[0]) == len(records)
    assert got[0] == got[1]


def test_an_unknown_subprotocol_is_still_refused() -> None:
    from websockets.exceptions import InvalidStatus

    feed = FoxgloveFeed(SinkContext(), "127.0.0.1", 0)
    try:
        with pytest.raises(InvalidStatus, match="400"):
            connect(feed.url, subprotocols=["foxglove.websocket.v2"], open_timeout=10)
    finally:
        feed.close()


def test_port_in_use_is_a_sink_error() -> None:
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        with pytest.raises(SinkError, match=rf"127\.0\.0\.1:{port}: cannot listen: .*in use"):
            FoxgloveFeed(SinkContext(), "127.0.0.1", port)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("8765", ("127.0.0.1", 8765)),  # a bare port listens on loopback
        ("0", ("127.0.0.1", 0)),
        ("0.0.0.0:9000", ("0.0.0.0", 9000)),
        ("localhost:1", ("localhost", 1)),
        ("[::1]:8765", ("::1", 8765)),
    ],
)
def test_foxglove_address(text: str, expected: tuple[str, int]) -> None:
    assert foxglove_address(text) == expected


@pytest.mark.parametrize("text", ["lo", "70000", ":", "host:", "-1", "[::1]8765", "a b:1"])
def test_bad_foxglove_address(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError):
        foxglove_address(text)


def test_bare_option_is_loopback_8765() -> None:
    from mbmon.cli import build_parser

    parser = build_parser()
    for argv in (["replay", "x.mcap", "--foxglove"], ["sniff", "lo", "--foxglove"]):
        assert parser.parse_args(argv).foxglove == FOXGLOVE_DEFAULT == ("127.0.0.1", 8765)
    assert parser.parse_args(["sniff", "lo"]).foxglove is None


# --------------------------------------------------------------------------- the CLI


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _url_from(proc: subprocess.Popen[bytes], timeout: float = 20.0) -> tuple[str, bytes]:
    """Read the process's stderr until it says where the feed listens."""
    import select

    assert proc.stderr is not None
    err = b""
    end = time.monotonic() + timeout
    while True:
        m = re.search(rb"Foxglove live feed on (ws://[^\s;]+)", err)
        if m:
            return m.group(1).decode(), err
        left = end - time.monotonic()
        if left <= 0 or proc.poll() is not None:
            raise AssertionError(f"no feed address; stderr: {err.decode()}")
        ready, _, _ = select.select([proc.stderr], [], [], left)
        if ready:
            err += os.read(proc.stderr.fileno(), 4096)


def _replay_served(
    argv: list[str], wanted: list[str], check: Callable[[str, Client], None] | None = None
) -> tuple[int, bytes, bytes, list[tuple[str, int, bytes]]]:
    """``mbmon replay ARGV`` with its feed: a client reads the advertised ``wanted``
    channels (``check(url, client)`` then), subscribes to them and takes what is served
    until replay ends. Replay's exit status, stdout, stderr and the messages served."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "replay", *argv],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(), cwd=REPO,
    )  # fmt: skip
    try:
        url, _err = _url_from(proc)
        client = Client(url)
        client.read_advertised(set(wanted))
        if check is not None:
            check(url, client)
        client.subscribe(wanted)
        out, err = proc.communicate(timeout=60)
        client.closed.wait(10)  # the server stops when replay ends
        got = client.messages()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, out, err, got


@pytest.fixture
def hrss_log(tmp_path: Path, hrss_stream: list) -> Path:
    path = tmp_path / "hrss.mcap"
    with open_sink(path, hrss_context()) as sink:
        _feed_like_the_hub(sink, hrss_stream)
    return path


@pytest.mark.parametrize("redecode", [False, True], ids=["stored", "redecode"])
def test_replay_serves_the_logs_messages_paced(hrss_log: Path, redecode: bool) -> None:
    """``replay --foxglove 127.0.0.1:0 --speed``: a client gets the log's own messages
    (stored; or re-decoded by today's decoder, which made the log: the same bytes)."""

    def check(url: str, client: Client) -> None:
        assert url.startswith("ws://127.0.0.1:")  # loopback unless a host is named
        assert set(client.channels) == set(topics(True))

    wanted = ["/modbus/monitor", "/hrss/state"]
    argv = [str(hrss_log), "--foxglove", "127.0.0.1:0", "--speed", "0.05"]
    status, out, err, got = _replay_served(
        argv + (["--redecode"] if redecode else []), wanted, check
    )
    assert status == 0, err.decode()
    expected = _log_messages(hrss_log, set(wanted))
    # live: what was served after the client subscribed, up to the end of the log
    assert got, "nothing received"
    assert got == expected[len(expected) - len(got) :]
    assert len(got) > len(expected) // 2  # 0.4 s of capture paced over 8 s
    assert any(t == "/hrss/state" for t, _, _ in got)
    lines = out.decode().splitlines()
    monitor_lines = [json.loads(p)["message"] for t, _, p in got if t == "/modbus/monitor"]
    assert monitor_lines == lines[len(lines) - len(monitor_lines) :]  # what replay printed


def test_replay_with_filters_serves_only_the_printed_records(hrss_log: Path) -> None:
    status, out, err, got = _replay_served(
        [str(hrss_log), "--fc", "4", "--foxglove", "0", "--speed", "0.05"],
        ["/modbus/monitor", "/modbus/frames", "/modbus/raw"],
    )
    assert status == 0, err.decode()
    assert got
    assert {t for t, _, _ in got} <= {"/modbus/monitor", "/modbus/frames"}  # no raw: filtered
    assert all(_decoded(t, p)["fc"] == 4 for t, _, p in got if t == "/modbus/frames")
    printed = out.decode().splitlines()
    for t, _, p in got:
        obj = _decoded(t, p)
        if "message" in obj:
            assert obj["message"] in printed


def test_replay_port_in_use_is_one_line_exit_1(hrss_log: Path) -> None:
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        proc = subprocess.run(
            [sys.executable, "-m", "mbmon", "replay", str(hrss_log), "--foxglove", str(port)],
            capture_output=True, text=True, env=_env(), cwd=REPO, timeout=60,
        )  # fmt: skip
    assert proc.returncode == 1
    assert proc.stdout == ""
    assert proc.stderr.startswith(f"mbmon: --foxglove 127.0.0.1:{port}: cannot listen:")
    assert "in use" in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_missing_sdk_is_one_line_exit_2(hrss_log: Path, tmp_path: Path) -> None:
    """Without foxglove-sdk (its import fails), ``--foxglove`` says how to install it."""
    code = (
        "import sys; sys.modules['foxglove'] = None\n"  # what a missing package looks like
        "from mbmon.cli import main; sys.exit(main(sys.argv[1:]))"
    )
    for argv in (
        ["replay", str(hrss_log), "--foxglove"],
        ["sniff", "lo", "--port", "1", "--foxglove", "-q", "-w", str(tmp_path / "x.mcap")],
    ):
        proc = subprocess.run(
            [sys.executable, "-c", code, *argv],
            capture_output=True, text=True, env=_env(), cwd=REPO, timeout=60,
        )  # fmt: skip
        if argv[0] == "sniff" and "permission" in proc.stderr.lower():
            continue  # not root: the capture cannot open first
        lines = [ln for ln in proc.stderr.splitlines() if not ln.startswith("mbmon: sniffing")]
        assert proc.returncode == 2, proc.stderr
        assert lines == ["mbmon: --foxglove needs the foxglove-sdk package: "
                         "pip install 'mbmon[foxglove]'"]  # fmt: skip
    assert not (tmp_path / "x.mcap").exists()  # no log left half written


# --------------------------------------------------------------------------- sniff, live


@pytest.mark.skipif(
    not hasattr(os, "geteuid") or os.geteuid() != 0,
    reason="live capture needs root (an AF_PACKET socket); CI runs as root",
)
def test_sniff_feeds_a_client_what_the_log_of_the_run_holds(tmp_path: Path) -> None:
    """``sniff lo --profile hrss --foxglove 127.0.0.1:0 -w LOG``: the sim robot and the
    manual's program on 127.0.0.1; a client subscribed to /modbus/monitor and
    /hrss/state receives exactly the messages the MCAP log of the same run holds."""
    from mbmon.sim import SimServer, run_program

    sim = SimServer(port=0)
    host, port = sim.start()  # type: ignore[misc]
    log = tmp_path / "live.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "sniff", "lo", "--port", str(port), "--profile", "hrss",
         "--foxglove", "127.0.0.1:0", "-q", "-w", str(log)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(), cwd=REPO,
    )  # fmt: skip
    try:
        url, _err = _url_from(proc)
        assert url.startswith("ws://127.0.0.1:")
        wanted = ["/modbus/monitor", "/hrss/state"]
        client = Client(url)
        client.read_advertised(set(wanted))
        client.subscribe(wanted)
        time.sleep(1.0)  # the subscription reaches the server before the traffic starts
        run_program(host, port, extras=False)
        time.sleep(1.0)  # the last packets reach the sniffer
        proc.send_signal(2)
        _out, err = proc.communicate(timeout=30)
        client.closed.wait(10)
        got = client.messages()
    finally:
        sim.stop()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err.decode()
    expected = _log_messages(log, set(wanted))
    assert len(expected) > 20
    assert got == expected
    validators = _validators()
    for topic, _, payload in got:
        validators[topic].validate(json.loads(payload))
    states = [json.loads(p) for t, _, p in got if t == "/hrss/state"]
    assert states and all("a1" in s for s in states[-1:])


@pytest.mark.skipif(
    not hasattr(os, "geteuid") or os.geteuid() != 0,
    reason="live capture needs root (an AF_PACKET socket); CI runs as root",
)
def test_sniff_port_in_use_is_one_line_exit_1_and_no_log(tmp_path: Path) -> None:
    log = tmp_path / "never.mcap"
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        proc = subprocess.run(
            [sys.executable, "-m", "mbmon", "sniff", "lo", "--port", "1",
             "--foxglove", f"127.0.0.1:{port}", "-q", "-w", str(log)],
            capture_output=True, text=True, env=_env(), cwd=REPO, timeout=60,
        )  # fmt: skip
    assert proc.returncode == 1
    assert proc.stderr.startswith(f"mbmon: --foxglove 127.0.0.1:{port}: cannot listen:")
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not log.exists()


def test_demo_feeds_a_client_what_its_log_holds(tmp_path: Path) -> None:
    """``demo --keep-running --foxglove 127.0.0.1:0``: a client that subscribes while
    the demo keeps sim and proxy up sees a user's own read through the proxy, live,
    as the same messages the demo's MCAP log holds for it."""
    from pymodbus.client import ModbusTcpClient

    log = tmp_path / "d.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "demo", "--fast", "--plain", "--keep-running",
         "--foxglove", "127.0.0.1:0", "-w", str(log)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=_env(), cwd=tmp_path,
    )  # fmt: skip
    try:
        url, err = _url_from(proc)
        assert url.startswith("ws://127.0.0.1:")
        client = Client(url)
        client.read_advertised({"/modbus/monitor", "/hrss/state"})
        client.subscribe(["/modbus/monitor"])
        time.sleep(1.0)  # the subscription reaches the server before the read
        import select

        end = time.monotonic() + 60
        while not (m := re.search(rb"proxy 127\.0\.0\.1:(\d+) -> robot", err)):
            assert time.monotonic() < end and proc.poll() is None, err.decode()
            if select.select([proc.stderr], [], [], 1.0)[0]:
                err += os.read(proc.stderr.fileno(), 4096)  # type: ignore[union-attr]
        with ModbusTcpClient("127.0.0.1", port=int(m.group(1)), timeout=5, retries=0) as user:
            assert not user.read_input_registers(100, count=1, device_id=1).isError()
        end = time.monotonic() + 10
        while not any(b"04 02 00 5A" in p for _t, _lt, p in client.messages()):
            assert time.monotonic() < end, "the user's read never reached the client"
            time.sleep(0.05)
        got = client.messages()
        proc.send_signal(2)
        proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0
    lines = [json.loads(p)["message"] for _t, _lt, p in got]
    assert any("Send to client" in ln and "04 02 00 5A" in ln for ln in lines)  # R100 = 90
    logged = _log_messages(log, {"/modbus/monitor"})
    assert got and all(m in logged for m in got)


def test_proxy_feeds_a_client_what_its_log_holds(tmp_path: Path) -> None:
    """``proxy --foxglove 127.0.0.1:0 -w LOG`` in front of the sim: a subscribed client
    receives exactly the monitor lines and HRSS state the proxy's log holds."""
    import select

    from mbmon.sim import SimServer, run_program

    sim = SimServer(port=0)
    host, port = sim.start()  # type: ignore[misc]
    log = tmp_path / "proxy.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "proxy", "--upstream", f"{host}:{port}",
         "--listen", "127.0.0.1:0", "--profile", "hrss", "--foxglove", "127.0.0.1:0",
         "-q", "-w", str(log)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=_env(), cwd=REPO,
    )  # fmt: skip
    try:
        url, err = _url_from(proc)
        end = time.monotonic() + 30
        while not (m := re.search(rb"listening on 127\.0\.0\.1:(\d+) ->", err)):
            assert time.monotonic() < end and proc.poll() is None, err.decode()
            if select.select([proc.stderr], [], [], 1.0)[0]:
                err += os.read(proc.stderr.fileno(), 4096)  # type: ignore[union-attr]
        wanted = ["/modbus/monitor", "/hrss/state"]
        client = Client(url)
        client.read_advertised(set(wanted))
        client.subscribe(wanted)
        time.sleep(1.0)  # the subscription reaches the server before the traffic starts
        run_program("127.0.0.1", int(m.group(1)), extras=False)
        time.sleep(1.0)
        proc.send_signal(2)
        proc.communicate(timeout=30)
        client.closed.wait(10)
        got = client.messages()
    finally:
        sim.stop()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0
    expected = _log_messages(log, set(wanted))
    assert len(expected) > 20
    # the log may hold the proxy's start-up notice, sent before the client subscribed
    assert got == expected[len(expected) - len(got) :]
    assert any(t == "/hrss/state" for t, _, _ in got)


def test_replay_of_a_format_2_log_serves_protobuf(tmp_path: Path) -> None:
    """``replay --foxglove`` of a log written before format 3: its JSON frames and raw
    messages are served on the feed's protobuf channels as the format-3 messages of the
    same objects (what a format-3 log of the same capture would serve)."""
    from mbmon.io.mcap.layout import proto_payload

    old = REPO / "tests" / "io" / "data" / "format2" / "demo.mcap"
    if not old.exists():
        pytest.skip("the format-2 fixture is absent")

    def check(url: str, client: Client) -> None:
        assert client.channels["/modbus/frames"]["encoding"] == "protobuf"

    wanted = ["/modbus/frames", "/modbus/raw"]
    status, _out, err, got = _replay_served(
        [str(old), "--foxglove", "127.0.0.1:0", "--speed", "0.2"], wanted, check
    )
    assert status == 0, err.decode()
    with McapLog(old) as log:
        stored = [
            (m.topic, m.log_time, proto_payload(m.topic, json.loads(m.raw)))
            for m in log.messages(wanted)
        ]
    assert got, "nothing received"
    assert got == stored[len(stored) - len(got) :]  # from the subscription on
    for topic, _, payload in got:
        assert isinstance(_decoded(topic, payload), dict)
