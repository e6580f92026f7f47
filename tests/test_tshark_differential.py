"""Differential test: every Modbus ADU tshark dissects, ``mbmon read --json`` reports the same.

For every capture in ``../shared/captures/real/`` and in ``captures/``, tshark
(``-T json`` of the ``mbtcp``/``mbrtu`` and ``modbus`` layers) and mbmon each
list their ADUs. Per ADU they must agree on: direction (source and destination
``IP:PORT``), transaction id, unit id, function code (exception bit cleared),
exception code, and the reference number (address) and word/bit count whenever
tshark shows them. tshark shows no reference number or count on read responses
(mbmon carries the request's there, by design: docs/json.md), so those two are
compared where tshark has them, which is every request, every write response
and FC 0x17's read part.

The comparison is a multiset per (source, destination, transaction id, unit,
function code), so ordering differences do not matter, and it is strict both
ways:

* every tshark ADU must be matched by one mbmon ADU, except the ones listed in
  ``MBMON_MISSES`` (empty: mbmon must find everything tshark finds);
* every mbmon ADU must be matched by one tshark ADU, except the ones listed in
  ``TSHARK_DOES_NOT_FRAME``, each with the file, the frame and why tshark is
  wrong or silent there; for those, mbmon's own answer is asserted field by
  field, against the bytes of that frame.

A documented case that disappears (tshark or mbmon changed) fails the test too,
so the lists cannot go stale silently.

tshark runs once per file and mbmon once per file (cached for the session).
``EXTRA_ARGS`` gives per-file options (e.g. ``-d tcp.port==1502,mbtcp`` /
``--port 1502`` for a server on port 1502; no file in the corpus needs one
today). The whole module runs in well under two minutes.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections import defaultdict
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[1]
REAL = REPO / ".." / "shared" / "captures" / "real"
OWN = REPO / "captures"

TSHARK = shutil.which("tshark")
pytestmark = pytest.mark.skipif(TSHARK is None, reason="tshark is not installed")

ADU_KINDS = ("request", "response", "exception")
USER0_AS_MBRTU = 'uat:user_dlts:"User 0 (DLT=147)","mbrtu","0","","0",""'

# file name -> (extra tshark options, extra mbmon options)
EXTRA_ARGS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "hrss_rtu.pcap": (("-o", USER0_AS_MBRTU), ()),
    "sim_rtu.pcap": (("-o", USER0_AS_MBRTU), ()),
}


@dataclass(frozen=True)
class Expected:
    """One ADU tshark does not report, with mbmon's answer spelled out."""

    frame: int  # the frame whose payload carries the ADU
    src: str
    dst: str
    tid: int
    unit: int
    fc: int
    kind: str
    pdu: str  # monitor-line hex (function code + data)
    noise_before: str | None  # hex of the noise mbmon reports just before it, same direction
    why: str
    # mbmon reports the ADU at this frame's time when its segment was held out of order
    # and released later (by the segment or acknowledgement that settled the hole)
    time_frame: int | None = None


# The server of digitalbond part 1 (also in arkime's merged capture) sends the 14 bytes
# 00 01 00 00 00 05 0A 2A 0E 04 01 01 01 23 twice (frames 111 and 113). The MBAP length
# 5 makes an 11-byte ADU, so 3 bytes (01 01 23) are left before frame 113. tshark
# dissects nothing in frame 113; neither does mbmon any more: the header found there
# after noise has a function code of unpredictable length (0x2A) and nothing
# corroborates it (no header lines up after it, the stream does not end there), so
# its bytes stay noise (DESIGN rule 4).

TSHARK_DOES_NOT_FRAME: dict[str, list[Expected]] = {
    # arkime's file merges the Digital Bond part1 and part2 streams (part1 first, so
    # the same frame numbers here)
    "tcp__zeek__fuzz-72.pcap": [
        Expected(
            frame=7,
            src="192.168.66.235:2582",
            dst="166.161.16.230:502",
            tid=0,
            unit=1,
            fc=0x22,
            kind="request",
            pdu="22 00 00 00 00",
            noise_before="00 00",
            why=(
                "Frame 6 is the 12-byte segment 00 00 00 00 00 04 01 21 00 00 00 00 whose "
                "MBAP length 4 makes a 10-byte ADU (FC 0x21), leaving 2 bytes (00 00) in "
                "the stream. tshark dissects frame 6's ADU and then shows frame 7 "
                "(00 00 00 00 00 06 01 22 00 00 00 00) as plain TCP; mbmon reports the 2 "
                "bytes as noise (length 0) and frames frame 7's FC 0x22 request."
            ),
        ),
        *(
            Expected(
                frame=frame,
                src="166.161.16.230:502",
                dst="192.168.66.235:2582",
                tid=0,
                unit=1,
                fc=fc,
                kind="exception",
                pdu=f"{fc | 0x80:02X} 01",
                noise_before=None,
                time_frame=time_frame,
                why=(
                    "Frame 1 is a fuzzed server segment with SYN+FIN+PSH+URG and 6 payload "
                    "bytes. mbmon ignores the FIN of a SYN+FIN segment (no valid TCP stack "
                    "accepts one), so the server direction stays open; each of these "
                    "server segments carries one complete 9-byte ADU (exception 01 to the "
                    "fuzzer's request) that tshark does not dissect as Modbus after that "
                    "frame. Frames 19 and 21 follow a hole in the server's sequence space "
                    "and are released when frame 22 acknowledges them, each with its own "
                    "frame's time, not frame 22's."
                ),
            )
            for frame, fc, time_frame in (
                (19, 0x2F, None),
                (21, 0x33, None),
                (26, 0x3A, None),
                (27, 0x3B, None),
            )
        ),
    ],
}

# file name -> {frame number: why mbmon does not report tshark's ADU there}
MBMON_MISSES: dict[str, dict[int, str]] = {}


# --------------------------------------------------------------------------- the two views


@dataclass(frozen=True)
class Adu:
    """The fields both tools report for one ADU (``address``/``count`` None when absent)."""

    src: str
    dst: str
    tid: int | None
    unit: int
    fc: int
    exc: int | None
    address: int | None
    count: int | None
    frame: int = 0  # tshark's frame number (0 for mbmon ADUs)
    record: int = -1  # mbmon's record index (-1 for tshark ADUs)


def _as_list(x: Any) -> list[Any]:
    if x is None:
        return []
    return x if isinstance(x, list) else [x]


def _modbus_fields(d: dict[str, Any]) -> tuple[int, int | None, int | None, int | None]:
    fc = int(d["modbus.func_code"])
    exc = int(d["modbus.exception_code"]) if "modbus.exception_code" in d else None
    address = count = None
    for k in ("modbus.reference_num", "modbus.read_reference_num"):
        if k in d:
            address = int(d[k])
    for k in ("modbus.word_cnt", "modbus.bit_cnt", "modbus.read_word_cnt"):
        if k in d:
            count = int(d[k])
    return fc, exc, address, count


@cache
def tshark_adus(path: Path) -> tuple[Adu, ...]:
    """Every ADU tshark dissects, in frame order (several per frame when a segment holds several).

    In tshark's JSON a frame's ``mbtcp`` (or ``mbrtu``) layers and its ``modbus``
    layers come as two lists, one entry per ADU in order; they are paired by
    position, and a frame where the two lists differ in length fails loudly.
    """
    extra = EXTRA_ARGS.get(path.name, ((), ()))[0]
    cmd = [
        TSHARK or "tshark",
        "-r",
        str(path),
        *extra,
        "-Y",
        "mbtcp or mbrtu",
        "-T",
        "json",
        "--no-duplicate-keys",
        "-j",
        "frame ip ipv6 tcp udp mbtcp mbrtu modbus",
    ]
    out = subprocess.run(cmd, capture_output=True, check=True).stdout
    adus: list[Adu] = []
    for pkt in json.loads(out or b"[]"):
        layers = pkt["_source"]["layers"]
        frame = int(layers["frame"]["frame.number"])
        if "ip" in layers:
            sip, dip = layers["ip"]["ip.src"], layers["ip"]["ip.dst"]
        elif "ipv6" in layers:
            sip, dip = f"[{layers['ipv6']['ipv6.src']}]", f"[{layers['ipv6']['ipv6.dst']}]"
        else:  # RTU records: mbmon names both ends after the file
            sip = dip = ""
        l4 = layers.get("tcp") or layers.get("udp")
        if l4 is not None:
            proto = "tcp" if "tcp" in layers else "udp"
            src = f"{sip}:{l4[f'{proto}.srcport']}"
            dst = f"{dip}:{l4[f'{proto}.dstport']}"
        else:
            src = dst = path.name
        heads = _as_list(layers.get("mbtcp")) or _as_list(layers.get("mbrtu"))
        bodies = _as_list(layers.get("modbus"))
        assert len(heads) == len(bodies), (
            f"{path.name} frame {frame}: {len(heads)} ADU headers but {len(bodies)} Modbus "
            "PDUs in tshark's output; cannot pair them"
        )
        for head, body in zip(heads, bodies, strict=True):
            fc, exc, address, count = _modbus_fields(body)
            tid = int(head["mbtcp.trans_id"]) if "mbtcp.trans_id" in head else None
            unit = int(head.get("mbtcp.unit_id", head.get("mbrtu.unit_id", -1)))
            adus.append(Adu(src, dst, tid, unit, fc, exc, address, count, frame=frame))
    return tuple(adus)


@dataclass(frozen=True)
class MbmonRun:
    rc: int
    stderr: str
    records: tuple[dict[str, Any], ...]


@cache
def mbmon_run(path: Path) -> MbmonRun:
    """``mbmon read FILE --json``, parsed."""
    extra = EXTRA_ARGS.get(path.name, ((), ()))[1]
    p = subprocess.run(
        [sys.executable, "-m", "mbmon", "read", str(path), "--json", *extra], capture_output=True
    )
    records = []
    for line in p.stdout.splitlines():
        records.append(json.loads(line))
    return MbmonRun(p.returncode, p.stderr.decode(errors="replace"), tuple(records))


def mbmon_adus(path: Path) -> tuple[Adu, ...]:
    out = []
    for r in mbmon_run(path).records:
        if r["kind"] in ADU_KINDS:
            out.append(
                Adu(
                    r["src"],
                    r["dst"],
                    r["tid"],
                    r["unit"],
                    r["fc"],
                    r["exception_code"],
                    r["address"],
                    r["count"],
                    record=r["index"],
                )
            )
    return tuple(out)


def match(ts: tuple[Adu, ...], mb: tuple[Adu, ...]) -> tuple[int, list[Adu], list[Adu]]:
    """Pair tshark ADUs with mbmon ADUs: (matched count, unmatched tshark, unmatched mbmon).

    Candidates share source, destination, transaction id, unit and function
    code; among them the first that also agrees on the exception code and on
    address/count where tshark gives them is taken.
    """
    pool: dict[tuple[Any, ...], list[Adu]] = defaultdict(list)
    for a in mb:
        pool[(a.src, a.dst, a.tid, a.unit, a.fc)].append(a)
    matched = 0
    missing: list[Adu] = []
    for t in ts:
        candidates = pool.get((t.src, t.dst, t.tid, t.unit, t.fc), [])
        for i, a in enumerate(candidates):
            if (
                a.exc == t.exc
                and (t.address is None or a.address == t.address)
                and (t.count is None or a.count == t.count)
            ):
                del candidates[i]
                matched += 1
                break
        else:
            missing.append(t)
    extra = sorted((a for rest in pool.values() for a in rest), key=lambda a: a.record)
    return matched, missing, extra


# --------------------------------------------------------------------------- the files


def _files() -> list[Any]:
    params: list[Any] = []
    if REAL.is_dir():
        params += [pytest.param(p, id=p.name) for p in sorted(REAL.glob("tcp__*"))]
    else:
        params.append(
            pytest.param(
                None,
                id="real-captures",
                marks=pytest.mark.skip(reason=f"{REAL} absent (real captures are not shipped)"),
            )
        )
    params += [pytest.param(p, id=p.name) for p in sorted(OWN.glob("*.pcap"))]
    return params


FILES = _files()


@pytest.mark.parametrize("path", FILES)
def test_mbmon_reads_the_file_cleanly(path: Path) -> None:
    run = mbmon_run(path)
    rc, clean = run.rc, "Traceback" not in run.stderr
    assert rc == 0 and clean, f"mbmon read {path.name} --json exited {rc}:\n{run.stderr[-3000:]}"


@pytest.mark.parametrize("path", FILES)
def test_every_tshark_adu_is_found_by_mbmon(path: Path) -> None:
    ts = tshark_adus(path)
    assert ts, f"tshark found no Modbus in {path.name}: wrong options?"
    _, missing, _ = match(ts, mbmon_adus(path))
    allowed = MBMON_MISSES.get(path.name, {})
    unexplained = [t for t in missing if t.frame not in allowed]
    assert not unexplained, (
        f"{len(unexplained)} of {len(ts)} tshark ADUs in {path.name} have no mbmon match, "
        "first ones:\n" + "\n".join(map(str, unexplained[:10]))
    )
    assert {t.frame for t in missing} == set(allowed), "a documented miss no longer happens"


@pytest.mark.parametrize("path", FILES)
def test_every_mbmon_adu_is_tshark_s_or_documented(path: Path) -> None:
    _, _, extra = match(tshark_adus(path), mbmon_adus(path))
    expected = TSHARK_DOES_NOT_FRAME.get(path.name, [])
    records = mbmon_run(path).records
    got = [records[a.record] for a in extra]
    assert len(got) == len(expected), (
        f"mbmon reports {len(got)} ADUs in {path.name} that tshark does not, "
        f"{len(expected)} documented:\n" + "\n".join(r["line"] for r in got[:10])
    )
    for rec, exp in zip(got, expected, strict=True):
        assert (
            rec["src"],
            rec["dst"],
            rec["tid"],
            rec["unit"],
            rec["fc"],
            rec["kind"],
            rec["pdu"],
        ) == (exp.src, exp.dst, exp.tid, exp.unit, exp.fc, exp.kind, exp.pdu), exp.why
        # the ADU really is in that frame: same time, and its PDU bytes are in the payload
        _, payload = _frame(path, exp.frame)
        time, _ = _frame(path, exp.time_frame or exp.frame)
        assert abs(rec["time"] - time) < 1e-5, (rec["time"], time, exp.why)
        assert exp.pdu.replace(" ", "").lower() in payload, (payload, exp.why)
        if exp.noise_before is not None:
            before = [
                r for r in records[: rec["index"]] if r["kind"] == "noise" and r["src"] == exp.src
            ]
            assert before and before[-1]["pdu"] == exp.noise_before, (before[-1:], exp.why)


@cache
def _frame(path: Path, number: int) -> tuple[float, str]:
    out = subprocess.run(
        [
            TSHARK or "tshark",
            "-r",
            str(path),
            "-Y",
            f"frame.number=={number}",
            "-T",
            "fields",
            "-e",
            "frame.time_epoch",
            "-e",
            "tcp.payload",
        ],
        capture_output=True,
        check=True,
        text=True,
    ).stdout.split("\t")
    return float(out[0]), out[1].strip().replace(":", "")


def test_part1_stream_of_0x8804_lengths_is_noise_for_both() -> None:
    """Digital Bond part1, client 10.0.0.57:2585: two 451-byte segments of back-to-back
    MBAP headers with length 0x8804 (34820, far over 254) and two 12-byte segments with
    protocol id 0x0010. tshark dissects nothing there; mbmon must frame nothing either and
    report every payload byte of that direction as noise (none silently dropped)."""
    path = REAL / "tcp__digitalbond__modbus_test_data_part1.pcap"
    if not path.exists():
        pytest.skip(f"{REAL} absent (real captures are not shipped)")
    client = "10.0.0.57:2585"
    assert not [a for a in tshark_adus(path) if client in (a.src, a.dst)]
    records = [r for r in mbmon_run(path).records if r["src"] == client]
    assert not [r for r in records if r["kind"] in ADU_KINDS]
    noise = sum(len(r["pdu"].split()) for r in records if r["kind"] == "noise")
    out = subprocess.run(
        [
            TSHARK or "tshark",
            "-r",
            str(path),
            "-Y",
            "tcp.srcport==2585 and tcp.len>0 and not tcp.analysis.retransmission",
            "-T",
            "fields",
            "-e",
            "tcp.len",
        ],
        capture_output=True,
        check=True,
        text=True,
    ).stdout
    sent = sum(int(x) for x in out.split())
    assert sent == 926
    assert noise == sent
