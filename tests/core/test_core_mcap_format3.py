"""The core's log format 3 messages (``frame_pb``, the protobuf ``/modbus/raw`` chunk)
against the pure layout's encoder, byte for byte, on the members whose encoding has a
corner: an answer with no values (``[]``: no packed field, the ``extra`` member), bits
and coils, registers whose varints take one, two and three bytes, an exception code, a
latency; and what the core wrote decodes to the ``read --json`` objects."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from core_diff import ROOT, require_core
from gen import write_conversation
from mcap_diff import assert_same_log

from mbmon.io.mcap.reader import McapLog
from mbmon.protocol.encode import encode_read_request, encode_read_response
from mbmon.protocol.mbap import encode_adu

PAIRS = [
    (encode_read_request(1, 10, 0), bytes([1, 0])),  # coils, byte count 0: values []
    (encode_read_request(1, 7, 11), encode_read_response(1, [1, 0, 1, 1, 0, 0, 0, 1, 1, 1, 0])),
    (encode_read_request(3, 100, 4), encode_read_response(3, [0, 0x7F, 0x80, 0xFFFF])),
    (bytes([5, 0, 3, 0xFF, 0]), bytes([5, 0, 3, 0xFF, 0])),  # a coil ON: values [1]
    (encode_read_request(4, 0, 1), bytes([0x84, 2])),  # an exception
]


def test_corner_members_are_byte_identical(tmp_path: Path) -> None:
    require_core()
    segments = []
    for tid, (req, resp) in enumerate(PAIRS, 1):
        segments += [(True, encode_adu(tid, 1, req)), (False, encode_adu(tid, 1, resp))]
    path = write_conversation(tmp_path / "corners.pcap", segments)
    assert assert_same_log(path, tmp_path, covered=True) is None
    log = tmp_path / "x.mcap"
    run = [sys.executable, "-m", "mbmon", "read", str(path)]
    subprocess.run([*run, "-q", "-w", str(log)], cwd=ROOT, check=True)
    printed = subprocess.run([*run, "--json"], cwd=ROOT, check=True, capture_output=True)
    want = [json.loads(line) for line in printed.stdout.splitlines()]
    want = {o["index"]: o for o in want if o["kind"] != "event"}
    with McapLog(log) as mlog:
        assert mlog.schema_of("/modbus/frames")[1] == "protobuf"  # type: ignore[index]
        got = {o["index"]: o for o in (m.json() for m in mlog.messages(["/modbus/frames"]))}
    assert got.keys() == want.keys()
    marked = [obj.pop("chunk") for obj in got.values() if "chunk" in obj]  # format 4's
    assert len(marked) == len(got)  # every ADU here is a whole segment: its chunk left out
    for index, obj in got.items():
        assert obj == {k: v for k, v in want[index].items() if v is not None and k != "line"}
    assert [o.get("values") for o in got.values()][1] == []
