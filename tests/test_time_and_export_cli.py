"""Through the CLI: one time basis (-t on replay/info/export), impossible timestamps,
untimed raw RTU dumps, disk full names the file, and ``export -o x.pcap`` writing one
ADU per TCP segment."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mbmon.io.pcap import LINKTYPE_ETHERNET, PcapngWriter, PcapWriter, TcpConversation
from mbmon.protocol.mbap import encode_adu

REPO = Path(__file__).resolve().parents[1]
OWN = REPO / "captures"
ENV = {**os.environ, "PYTHONPATH": str(REPO), "TZ": "UTC"}
HAS_TSHARK = shutil.which("tshark") is not None


def mbmon(*args: str | Path, code: int = 0) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(
        [sys.executable, "-m", "mbmon", *map(str, args)],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=300,
    )
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == code, proc.stderr
    return proc


def conversation_packets(adus: int, t0: float) -> list[tuple[float, bytes]]:
    """A Modbus/TCP conversation whose ADUs are cut at every place, header included."""
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    packets = [(t0, f) for f in conv.open()]
    t = t0
    for k in range(adus // 2):
        req = encode_adu(k, 1, bytes.fromhex("0300000002"))
        resp = encode_adu(k, 1, bytes.fromhex("030400070008"))
        for from_client, adu in ((True, req), (False, resp)):
            cut = 1 + k % (len(adu) - 1)  # 1..len-1: inside the MBAP header for most
            for part in (adu[:cut], adu[cut:]):
                t += 0.001
                packets.append((t, conv.send(from_client, part)))
    t += 0.01
    packets += [(t, f) for f in conv.close()]
    return packets


def split_capture(path: Path, adus: int = 40, t0: float = 1714564800.0) -> Path:
    with PcapWriter(path, LINKTYPE_ETHERNET) as writer:
        for ts, frame in conversation_packets(adus, t0):
            writer.write(ts, frame)
    return path


def tshark_tids(path: Path) -> list[str]:
    out = subprocess.run(
        ["tshark", "-r", str(path), "-Y", "mbtcp", "-T", "fields", "-e", "mbtcp.trans_id"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return [tid for line in out.splitlines() for tid in line.split(",") if tid]


# --------------------------------------------------------- export: one ADU per segment


@pytest.mark.skipif(not HAS_TSHARK, reason="tshark not installed")
def test_export_pcap_gives_wireshark_every_adu(tmp_path: Path) -> None:
    capture = split_capture(tmp_path / "split.pcap", adus=40)
    assert len(tshark_tids(capture)) < 40  # tshark loses ADUs whose header is split
    log = tmp_path / "s.mcap"
    live = [json.loads(x) for x in mbmon("read", capture, "--json", "-w", log).stdout.splitlines()]
    frames = [o for o in live if o["kind"] in ("request", "response")]
    assert len(frames) == 40
    out = tmp_path / "one.pcap"
    mbmon("export", log, "-o", out)
    tids = tshark_tids(out)
    assert len(tids) == 40  # every ADU dissected
    assert [int(t) for t in tids] == [o["tid"] for o in frames]
    fields = ["-e", "tcp.analysis.flags", "-e", "frame.time_epoch"]
    rows = subprocess.run(
        ["tshark", "-r", str(out), "-Y", "mbtcp", "-T", "fields", *fields],
        capture_output=True, text=True, check=True,
    ).stdout.splitlines()  # fmt: skip
    assert all(not row.split("\t")[0] for row in rows)  # consistent sequence numbers
    times = [float(row.split("\t")[1]) for row in rows]
    assert times == pytest.approx([o["time"] for o in frames], abs=1e-6)  # original times
    again = [json.loads(x) for x in mbmon("read", out, "--json").stdout.splitlines()]
    keep = ("src", "dst", "tid", "unit", "fc", "kind", "pdu", "time")
    assert [{k: o[k] for k in keep} for o in again if o["kind"] != "event"] == [
        {k: o[k] for k in keep} for o in frames
    ]  # original endpoints and bytes
    kept = tmp_path / "kept.pcap"
    mbmon("export", log, "-o", kept, "--keep-segments")
    assert len(tshark_tids(kept)) < 40  # the original segmentation, as asked


# --------------------------------------------------------------------- one time basis


def test_replay_info_and_export_share_the_time_basis(tmp_path: Path) -> None:
    capture = split_capture(tmp_path / "c.pcap", adus=6)
    log = tmp_path / "c.mcap"
    live = mbmon("read", capture, "-w", log).stdout.splitlines()
    assert live[0].startswith("12:00:00.000000  ")  # TZ=UTC
    assert mbmon("replay", log).stdout.splitlines() == live
    rel = mbmon("replay", log, "-t", "r").stdout.splitlines()
    assert [x.split("  ", 1)[1] for x in rel] == [x.split("  ", 1)[1] for x in live]
    assert rel[0].startswith("0.000000  ") and rel[2].startswith("0.00")
    epoch = mbmon("replay", log, "-t", "e").stdout.splitlines()
    assert epoch[0].startswith("1714564800.000000  ")
    dated = mbmon("replay", log, "-t", "ud").stdout.splitlines()
    assert dated[0].startswith("2024-05-01 12:00:00.000000  ")
    # --since/--until accept what each mode prints
    for mode, lines in (("a", live), ("r", rel), ("e", epoch), ("ud", dated)):
        since, until = lines[2].split("  ")[0], lines[4].split("  ")[0]
        got = mbmon("replay", log, "-t", mode, "--since", since, "--until", until).stdout
        assert got.splitlines() == lines[2:5], mode
    as_json = [json.loads(x) for x in mbmon("replay", log, "-t", "r", "--json").stdout.splitlines()]
    assert [o["line"] for o in as_json] == rel and as_json[0]["time"] == 1714564800.0
    text = tmp_path / "x.txt"
    mbmon("export", log, "-o", text, "-t", "r")
    assert text.read_text("utf-8").splitlines() == rel
    info = mbmon("info", log).stdout
    assert "time span:   2024-05-01 12:00:00.000000 .. 2024-05-01 12:00:00." in info
    assert " ms)" in info  # the span in human units
    assert "1714564800.000000 .. " in mbmon("info", log, "-t", "e").stdout


def test_a_capture_across_midnight_prints_dates(tmp_path: Path) -> None:
    capture = split_capture(tmp_path / "m.pcap", adus=4, t0=1714607999.995)  # 23:59:59.995
    live = mbmon("read", capture).stdout.splitlines()
    assert live[0].startswith("23:59:59.995000  ")
    assert live[-1].startswith("2024-05-02 00:00:00.")  # another day: the date shows
    log = tmp_path / "m.mcap"
    mbmon("read", capture, "-q", "-w", log)
    replayed = mbmon("replay", log).stdout.splitlines()
    assert replayed == live  # one time basis: replay prints what read printed
    start = replayed[-1].split("  ")[0]
    assert mbmon("replay", log, "--since", start).stdout.splitlines() == replayed[-1:]


# ------------------------------------------------------------------ impossible times


@pytest.mark.parametrize("when", [1e17, 1.7e12, 1.8e19])
def test_impossible_timestamps_print_and_every_sink_writes(tmp_path: Path, when: float) -> None:
    """A pcapng whose timestamps no calendar shows: every line prints (epoch seconds),
    CSV and pcap sinks write the records, the pcap sink says what it did."""
    capture = tmp_path / "bad.pcapng"
    good = conversation_packets(4, 1714564800.0)
    with PcapngWriter(capture) as writer:
        iface = writer.add_interface(LINKTYPE_ETHERNET, tsresol=0)  # 1 s units: up to 1.8e19
        for k, (ts, frame) in enumerate(good):
            writer.write(when + k if k >= 6 else round(ts), frame, interface=iface)
    lines = mbmon("read", capture).stdout.splitlines()
    as_json = mbmon("read", capture, "--json").stdout
    assert [json.loads(x)["line"] for x in as_json.splitlines()] == lines
    general = subprocess.run(
        [sys.executable, "-m", "mbmon", "read", str(capture), "--json"],
        capture_output=True, text=True, env={**ENV, "MBMON_NO_FASTLANE": "1"}, timeout=300,
    ).stdout  # fmt: skip
    assert general == as_json  # the fused reader hands impossible times to the general flow
    assert sum("[u1 t" in line for line in lines) == 4
    heads = [line.split("  ")[0] for line in lines]
    assert any(":" not in head and float(head) >= when for head in heads)  # epoch seconds
    out_csv, out_pcap = tmp_path / "x.csv", tmp_path / "x.pcap"
    proc = mbmon("read", capture, "-q", "-w", out_csv, "-w", out_pcap)
    with out_csv.open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 4 and all(r["utc"] for r in rows)
    assert "capture time a pcap cannot hold" in proc.stderr
    again = [json.loads(x) for x in mbmon("read", out_pcap, "--json").stdout.splitlines()]
    assert sum(o["kind"] in ("request", "response") for o in again) == 4  # every ADU kept


# --------------------------------------------------------------- untimed raw RTU dumps


def test_raw_rtu_dump_shows_no_made_up_times(tmp_path: Path) -> None:
    dump = OWN / "hrss_rtu.bin"
    lines = mbmon("read", "--rtu-raw", dump).stdout.splitlines()
    assert lines and all(line.startswith("#") for line in lines)
    assert not any("00:00:00" in line or " ms)" in line for line in lines)
    objs = [json.loads(x) for x in mbmon("read", "--rtu-raw", dump, "--json").stdout.splitlines()]
    assert all(o["time"] is None and o["latency_ms"] is None for o in objs)
    assert [o["line"] for o in objs] == lines
    assert any(o["request_index"] is not None for o in objs)  # still paired


# ---------------------------------------------------------- disk full names the file


@pytest.mark.parametrize("suffix", [".jsonl", ".csv", ".txt", ".pcap"])
def test_full_disk_names_the_file(tmp_path: Path, suffix: str) -> None:
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full on this machine")
    target = tmp_path / f"full{suffix}"
    target.symlink_to("/dev/full")
    proc = mbmon("read", OWN / "hrss_ptp.pcap", "-q", "-w", target, code=1)
    assert f"{target}: No space left on device" in proc.stderr
    log = tmp_path / "h.mcap"
    mbmon("read", OWN / "hrss_ptp.pcap", "-q", "-w", log)
    proc = mbmon("export", log, "-o", target, code=1)
    assert str(target) in proc.stderr and "No space left on device" in proc.stderr
