"""``mbmon export LOG -o x.pcap``: Wireshark (tshark, run for real) reads the export whole.

* A session whose server is on a port other than 502 decodes with no option:
  the server port is written as 502 (``--server-port``) and a note names the
  original; ``--keep-port`` keeps it and prints the exact tshark option, which
  is then enough.
* A capture that lost a segment: the export numbers its segments on (no hole
  for tshark's reassembly to wait on) and says where bytes were lost; bytes
  mbmon could not frame never start a Modbus reassembly that would swallow the
  ADUs after them. tshark sees every ADU mbmon framed.
* RTU buses: one ADU per record, so tshark (told link type 147 is Modbus RTU)
  decodes every frame, also where one serial read held a request and its answer.

tshark is required; the tests skip with a reason without it.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mbmon.io.pcap import (
    LINKTYPE_USER0,
    PcapWriter,
    TcpConversation,
    udp_frame,
)
from mbmon.protocol.crc import crc16
from mbmon.protocol.mbap import encode_adu

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "TZ": "UTC"}
TSHARK = shutil.which("tshark")
pytestmark = pytest.mark.skipif(TSHARK is None, reason="tshark is not installed")
USER0_AS_MBRTU = 'uat:user_dlts:"User 0 (DLT=147)","mbrtu","0","","0",""'
T0 = 1_714_564_800.0


def mbmon(*args: str | Path, code: int = 0, cwd: Path | None = None) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [sys.executable, "-m", "mbmon", *map(str, args)],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=300,
        cwd=cwd,
    )
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == code, proc.stderr
    return proc


def tshark(path: Path, *options: str, display: str = "modbus") -> list[list[str]]:
    """One row per packet tshark shows for ``display``: transaction ids, function codes
    (comma-joined when a packet carries several ADUs) and TCP analysis flags."""
    assert TSHARK is not None
    fields = ["-e", "mbtcp.trans_id", "-e", "modbus.func_code", "-e", "tcp.analysis.flags"]
    out = subprocess.run(
        [TSHARK, "-r", str(path), *options, "-Y", display, "-T", "fields", *fields],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout
    return [line.split("\t") for line in out.splitlines()]


def adus_seen(rows: list[list[str]], column: int = 1) -> int:
    return sum(len([x for x in row[column].split(",") if x]) for row in rows)


def mbmon_frames(capture: Path, *options: str) -> list[dict]:
    out = mbmon("read", capture, "--json", *options).stdout
    objs = [json.loads(line) for line in out.splitlines()]
    return [o for o in objs if o["kind"] in ("request", "response", "exception")]


def log_of(capture: Path, tmp_path: Path, *options: str) -> Path:
    log = tmp_path / f"{capture.stem}.mcap"
    mbmon("read", capture, "-q", "-w", log, *options)
    return log


def tcp_capture(path: Path, server: str, transactions: int = 30) -> Path:
    conv = TcpConversation("10.0.0.2:40000", server)
    with PcapWriter(path) as w:
        ts = T0
        for frame in conv.open():
            w.write(ts, frame)
        for tid in range(1, transactions + 1):
            ts += 0.01
            w.write(ts, conv.send(True, encode_adu(tid, 1, bytes.fromhex("0300640002"))))
            ts += 0.002
            w.write(ts, conv.send(False, encode_adu(tid, 1, bytes.fromhex("030400070008"))))
        for frame in conv.close():
            w.write(ts, frame)
    return path


# --------------------------------------------------------------------------- ports


def test_a_session_on_another_port_decodes_with_no_option(tmp_path: Path) -> None:
    capture = tcp_capture(tmp_path / "p1502.pcap", "10.0.0.1:1502")
    frames = mbmon_frames(capture, "--port", "1502")
    assert len(frames) == 60
    assert tshark(capture) == []  # as captured, tshark needs an option
    out = tmp_path / "d.pcap"
    err = mbmon("export", log_of(capture, tmp_path, "--port", "1502"), "-o", out).stderr
    assert "server port 1502 written as 502" in err
    rows = tshark(out)
    assert adus_seen(rows) == len(frames)
    assert [int(r[0]) for r in rows] == [f["tid"] for f in frames]
    assert not any(r[2] for r in rows), "TCP analysis flags: inconsistent numbering"
    # the export reads back in mbmon as the same frames (on 502 now)
    again = mbmon_frames(out)
    assert [(f["tid"], f["kind"], f["pdu"]) for f in again] == [
        (f["tid"], f["kind"], f["pdu"]) for f in frames
    ]
    assert {f["dst"] for f in again if f["kind"] == "request"} == {"10.0.0.1:502"}


def test_keep_port_prints_the_option_tshark_needs(tmp_path: Path) -> None:
    capture = tcp_capture(tmp_path / "p1502.pcap", "10.0.0.1:1502")
    out = tmp_path / "k.pcap"
    log = log_of(capture, tmp_path, "--port", "1502")
    err = mbmon("export", log, "-o", out, "--keep-port").stderr
    assert tshark(out) == []  # the port kept: no Modbus without the option
    match = re.search(r"tshark -r \S+ (.*?) \(Wireshark", err)
    assert match, err
    options = shlex.split(match.group(1))
    assert options == ["-d", "tcp.port==1502,mbtcp"]
    assert adus_seen(tshark(out, *options)) == 60  # the printed option is all it takes
    # a session on 502 needs no note at all
    plain = tcp_capture(tmp_path / "p502.pcap", "10.0.0.1:502")
    err = mbmon("export", log_of(plain, tmp_path), "-o", tmp_path / "p.pcap", "--keep-port").stderr
    assert "tshark" not in err and "written as" not in err
    # --server-port and --keep-port exclude each other
    mbmon("export", log, "-o", tmp_path / "x.pcap", "--keep-port", "--server-port", "502", code=2)


def test_a_udp_session_on_another_port_decodes_with_no_option(tmp_path: Path) -> None:
    capture = tmp_path / "udp.pcap"
    with PcapWriter(capture) as w:
        ts = T0
        for tid in range(1, 11):
            req = encode_adu(tid, 1, bytes.fromhex("0300640002"))
            resp = encode_adu(tid, 1, bytes.fromhex("030400070008"))
            w.write(ts, udp_frame(1, "10.0.0.2", "10.0.0.1", 40000, 1502, req))
            w.write(ts + 0.002, udp_frame(1, "10.0.0.1", "10.0.0.2", 1502, 40000, resp))
            ts += 0.01
    assert len(mbmon_frames(capture, "--port", "1502")) == 20
    out = tmp_path / "u.pcap"
    err = mbmon("export", log_of(capture, tmp_path, "--port", "1502"), "-o", out).stderr
    assert "Modbus/UDP server port 1502 written as 502" in err
    assert adus_seen(tshark(out, display="mbudp")) == 20


def test_the_demo_log_exports_for_wireshark(tmp_path: Path) -> None:
    """``mbmon demo`` serves its robot on a free port: the export decodes all the same."""
    mbmon("demo", "--fast", "--plain", cwd=tmp_path)
    log = tmp_path / "mbmon-demo.mcap"
    frames = [
        o
        for o in map(json.loads, mbmon("replay", log, "--json").stdout.splitlines())
        if o["kind"] in ("request", "response", "exception")
    ]
    port = frames[0]["dst"].rsplit(":", 1)[1]
    assert port != "502" and len(frames) > 50
    out = tmp_path / "d.pcap"
    err = mbmon("export", log, "-o", out).stderr
    assert f"server port {port} written as 502" in err
    # the guard's refusals are the proxy's own answers, on the proxy's own endpoint: the
    # same host as the robot's, so its port is kept (two servers never become one) and
    # the note gives the option that decodes it; every ADU of the robot decodes without
    proxy_frames = [o for o in frames if o["src"].split(":")[1] not in (port,) and
                    o["dst"].split(":")[1] not in (port,)]  # fmt: skip
    assert 0 < len(proxy_frames) < 5
    plain = adus_seen(tshark(out, display="mbtcp"), column=0)
    assert plain == len(frames) - len(proxy_frames)
    options = re.search(r"tshark -r \S+ (-d tcp\.port==\d+,mbtcp)", err)
    assert options is not None, err
    seen = adus_seen(tshark(out, *options.group(1).split(" ", 1), display="mbtcp"), column=0)
    assert seen == len(frames)


# --------------------------------------------------------------------------- losses


def lossy_capture(path: Path) -> Path:
    """Pipelined polls whose segments cut ADUs anywhere; one server segment is lost
    that held the first byte of a response: what follows it (``42 00 00 00 17 01 ...``)
    looks to tshark like an MBAP header asking for 5,895 bytes."""
    conv = TcpConversation("10.0.0.2:40000", "10.0.0.1:502")

    def resp(tid: int) -> bytes:
        return encode_adu(tid, 1, bytes([3, 20, *range(20)]))

    with PcapWriter(path) as w:
        ts = T0
        for frame in conv.open():
            w.write(ts, frame)
        tid = 0
        for batch in range(40):
            tids = range(tid + 1, tid + 4)
            tid += 3
            reqs = b"".join(encode_adu(t, 1, bytes.fromhex("030064000A")) for t in tids)
            resps = b"".join(resp(t) for t in tids)
            for from_client, data in ((True, reqs), (False, resps)):
                cuts = [0, 5, 17, 30, len(data)] if from_client else [0, 29, 30, 61, len(data)]
                for a, b in itertools.pairwise(cuts):
                    if a >= b:
                        continue
                    ts += 0.001
                    if batch == 10 and not from_client and a == 29:  # lost: 1 byte
                        conv.server_next += b - a
                        continue
                    w.write(ts, conv.send(from_client, data[a:b]))
        for frame in conv.close():
            w.write(ts, frame)
    return path


def test_a_lost_segment_costs_tshark_no_adu_mbmon_framed(tmp_path: Path) -> None:
    capture = lossy_capture(tmp_path / "lossy.pcap")
    frames = mbmon_frames(capture)
    assert len(frames) == 239  # 240 ADUs, one response lost its first byte
    out = tmp_path / "l.pcap"
    err = mbmon("export", log_of(capture, tmp_path), "-o", out).stderr
    assert "lost 1 byte(s) of Modbus/TCP in 1 place(s)" in err
    rows = tshark(out)
    assert adus_seen(rows) == len(frames)
    assert sorted(int(t) for r in rows for t in r[0].split(",")) == sorted(f["tid"] for f in frames)
    flags = tshark(out, display="tcp.analysis.lost_segment || tcp.analysis.ack_lost_segment")
    assert flags == [], "the export leaves a hole in the sequence numbers"


# --------------------------------------------------------------------------- RTU


def rtu(hexpdu: str, unit: int = 1) -> bytes:
    body = bytes([unit]) + bytes.fromhex(hexpdu)
    return body + crc16(body).to_bytes(2, "little")


def test_rtu_export_has_one_adu_per_record(tmp_path: Path) -> None:
    """Serial reads that hold a request and its answer together (a USB adapter's
    bursts) and reads that cut a frame: tshark decodes every frame of the export."""
    frames = []
    for n in range(8):
        frames.append(rtu(f"0300{n:02X}0002"))
        frames.append(rtu("030400070008"))
    bus = b"".join(frames)
    capture = tmp_path / "bus.pcap"
    with PcapWriter(capture, LINKTYPE_USER0) as w:
        ts = T0
        pos = 0
        for size in (16, 3, 22, 1, 40, 5, 60, 200):  # reads that ignore frame boundaries
            if pos >= len(bus):
                break
            w.write(ts, bus[pos : pos + size])
            pos += size
            ts += 0.02
    seen = mbmon_frames(capture)
    assert len(seen) == 16
    out = tmp_path / "r.pcap"
    err = mbmon("export", log_of(capture, tmp_path), "-o", out).stderr
    match = re.search(r"tshark -r \S+ (.*?) \(Wireshark", err)
    assert match, err
    options = shlex.split(match.group(1))  # the option the note prints, exactly
    assert options == ["-o", USER0_AS_MBRTU]
    rows = tshark(out, *options, display="mbrtu")
    assert adus_seen(rows) == 16
    assert len(rows) == 16  # one frame per record: nothing for tshark to reassemble


# --------------------------------------------------------------------------- pcapng


FIELDS_COMMENT = ["-e", "frame.number", "-e", "frame.comment"]


def comments_of(path: Path) -> list[tuple[int, str]]:
    """``(frame number, comment)`` of every packet comment tshark shows (4.x: the
    field is ``frame.comment``; several comments on one packet are comma-joined)."""
    assert TSHARK is not None
    out = subprocess.run(
        [TSHARK, "-r", str(path), "-Y", "frame.comment", "-T", "fields", *FIELDS_COMMENT],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout
    return [(int(n), text) for n, text in (line.split("\t", 1) for line in out.splitlines())]


def section_comments(path: Path) -> str:
    """The section header's comments, as ``capinfos`` prints them."""
    capinfos = shutil.which("capinfos")
    if capinfos is None:
        pytest.skip("capinfos (Wireshark's tools) is not installed")
    out = subprocess.run(
        [capinfos, str(path)], capture_output=True, text=True, timeout=120, check=True
    ).stdout
    return "\n".join(line for line in out.splitlines() if "comment" in line.lower())


def export_both(log: Path, tmp_path: Path, name: str) -> tuple[Path, Path, str]:
    """The log exported as ``NAME.pcap`` and ``NAME.pcapng``; the pcapng's stderr."""
    mbmon("export", log, "-o", tmp_path / f"{name}.pcap")
    err = mbmon("export", log, "-o", tmp_path / f"{name}.pcapng").stderr
    return tmp_path / f"{name}.pcap", tmp_path / f"{name}.pcapng", err


def read_lines(capture: Path) -> list[str]:
    return mbmon("read", capture, "--port", "502").stdout.splitlines()


def test_pcapng_export_marks_the_rewritten_port(tmp_path: Path) -> None:
    capture = tcp_capture(tmp_path / "p1502.pcap", "10.0.0.1:1502")
    pcap, pcapng, err = export_both(log_of(capture, tmp_path, "--port", "1502"), tmp_path, "p")
    assert pcapng.read_bytes()[:4] == b"\x0a\x0d\x0d\x0a"
    assert "server port 1502 written as 502" in err  # the stderr note stays
    assert adus_seen(tshark(pcapng)) == adus_seen(tshark(pcap)) == 60
    assert not any(r[2] for r in tshark(pcapng)), "TCP analysis flags"
    # the stream's first packet (its SYN) says what the port was; nothing else has a comment
    assert comments_of(pcapng) == [
        (1, "mbmon: server port 1502 in the original capture, written as 502")
    ]
    assert "Modbus/TCP server port 1502 in the original capture, written as 502" in (
        section_comments(pcapng)
    )
    lines = read_lines(pcapng)
    assert len(lines) > 60 and lines == read_lines(pcap)
    # a port kept as it was is no rewrite: no comment anywhere
    kept = tmp_path / "k.pcapng"
    mbmon("export", log_of(capture, tmp_path, "--port", "1502"), "-o", kept, "--keep-port")
    assert comments_of(kept) == [] and section_comments(kept) == ""


def test_pcapng_export_marks_the_loss(tmp_path: Path) -> None:
    pcap, pcapng, err = export_both(
        log_of(lossy_capture(tmp_path / "lossy.pcap"), tmp_path), tmp_path, "l"
    )
    assert "lost 1 byte(s) of Modbus/TCP in 1 place(s)" in err
    rows = tshark(pcapng)
    assert adus_seen(rows) == adus_seen(tshark(pcap)) == 239
    flags = tshark(pcapng, display="tcp.analysis.lost_segment || tcp.analysis.ack_lost_segment")
    assert flags == [], "the export leaves a hole in the sequence numbers"
    marked = comments_of(pcapng)
    assert [text for _n, text in marked] == [
        "mbmon: 1 byte of the server's stream was not captured before this segment "
        "(lost at 2024-05-01 12:00:00.088994 UTC)"
    ]
    # the comment is on the server's first segment after the loss: the rest of the response
    number = marked[0][0]
    fields = ["-e", "tcp.srcport", "-e", "tcp.len"]
    assert TSHARK is not None
    segment = subprocess.run(
        [TSHARK, "-r", str(pcapng), "-Y", f"frame.number == {number}", "-T", "fields", *fields],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout.split()
    assert segment[0] == "502" and int(segment[1]) > 0
    assert "1 byte(s) were not captured in 1 place(s)" in section_comments(pcapng)
    lines = read_lines(pcapng)
    assert len(lines) > 239 and lines == read_lines(pcap)
