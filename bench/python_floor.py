"""The least a pure-Python reader must spend per ADU on a Modbus/TCP capture.

    python bench/python_floor.py                  # 1,000,000 ADUs: floor stages, mbmon, tshark
    python bench/python_floor.py --adus 250000 --skip-tshark
    python bench/python_floor.py --realistic --adus 1000000   # the realistic capture

Why this exists: the target asks ``mbmon read --json`` for at least 5x tshark's
ADUs/s. This script measures how fast *any* Python code can go on the same
file on the same interpreter, so that the target can be judged against the
floor rather than against a guess. It is not mbmon and is never imported by it.

The floor is one flat loop, written for speed alone, in four stages; each stage
runs as its own child process (wall time and peak RSS of that child, as in
``read_throughput.py``), in the same run as ``mbmon read --json`` and tshark:

1. ``records``: pcap record headers, Ethernet/IPv4/TCP headers in one
   ``struct.unpack_from``, the payload sliced out.
2. ``framing``: plus the in-order check per connection direction and the MBAP
   length loop (ADUs split over segments joined, several per segment split).
3. ``pairing``: plus pairing by (connection, transaction id, unit) and latency.
4. ``json``: plus one JSON line per ADU with mbmon's keys, written to stdout in
   blocks: the per-PDU parts (function code, kind, address, count, values, hex,
   note) made once per distinct PDU and cached, as mbmon does; per record only
   index, time (epoch and time of day), stream head, ids, latency and request
   index are filled in, with the same ``%``-formatting mbmon uses.
5. ``text``: stage 4 with the monitor text line alone (``mbmon read`` without
   ``--json``): time of day, label, ids, hex, note and latency.

``--realistic`` runs the stages on the realistic polling capture
(``bench/realistic.py``: connections open before the capture, register values
that change every poll), where a cache of per-PDU parts misses on most
answers, so each of them pays its decode and note, as it must in any reader.

What the floor leaves out, and mbmon cannot: handshakes, FIN/RST and the
connect/disconnect records, retransmissions, out-of-order segments, gaps,
noise and resynchronisation, timeouts, unsolicited responses, exceptions and
bit reads decoded with their request, IPv6/VLAN/other link types, malformed
PDUs, labels for ``--robot``, counters, progress and error reporting. Every
one of those costs at least a test per packet or per ADU, so the floor is a
lower bound of mbmon's time, not an estimate of it.
"""

from __future__ import annotations

import argparse
import os
import struct
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from read_throughput import REPO, Run, capture, mbmon_cmd, measure, show, tshark_cmd

STAGES = ("records", "framing", "pairing", "json", "text")


def floor(path: str, stage: int) -> int:
    """Run floor stage ``stage`` (1..4) over the capture at ``path``; return the ADUs framed."""
    sys.path.insert(0, str(REPO))
    import orjson

    from mbmon.protocol.pdu import decode_pdu

    with open(path, "rb") as f:
        buf = f.read()
    unpack_rec = struct.Struct("<IIII").unpack_from
    unpack_net = struct.Struct("!12xHBxHxxHxB2x8sHHIIH").unpack_from
    dumps = orjson.dumps
    write = sys.stdout.buffer.write
    pos, n = 24, len(buf)
    conns: dict[tuple[bytes, int, int], list] = {}
    pending: dict[tuple[int, int, int], tuple[int, float, bytes]] = {}
    parts_of: dict[tuple[bytes, bool, int], tuple[bytes, bytes, bytes]] = {}
    lines: list[bytes] = []
    index = adus = 0
    clock = [-1.0, b""]
    while pos < n:
        sec, usec, caplen, _ = unpack_rec(buf, pos)
        off = pos + 16
        pos = off + caplen
        if stage < 2:
            unpack_net(buf, off)
            continue
        et, vihl, total, frag, proto, addrs, sport, dport, seq, _ack, hl = unpack_net(buf, off)
        if et != 0x0800 or vihl != 0x45 or proto != 6 or frag & 0x3FFF:
            continue
        doff = (hl >> 10) & 0x3C
        payload = buf[off + 34 + doff : off + 14 + total]
        key = (addrs, sport, dport)
        st = conns.get(key)
        if st is None:  # [next seq, held bytes, is client->server, stream id, head]
            src = "%d.%d.%d.%d:%d" % (*addrs[:4], sport)  # noqa: UP031
            dst = "%d.%d.%d.%d:%d" % (*addrs[4:], dport)  # noqa: UP031
            head = b',"stream":%d,"src":"%b","dst":"%b","transport":"tcp","tid":' % (
                len(conns) // 2,
                src.encode(),
                dst.encode(),
            )
            label = ("%s \xe2\x86\x92 %s" % (src, dst)).encode("latin-1")  # noqa: UP031
            conns[key] = [
                (seq + (1 if hl & 2 else 0)) & 0xFFFFFFFF,
                b"",
                dport == 502,
                len(conns) // 2,
                head,
                label,
            ]
            continue
        if st[0] != seq or hl & 7:  # handshake and FIN: only the sequence number kept
            st[0] = (seq + len(payload) + (1 if hl & 3 else 0)) & 0xFFFFFFFF
            continue
        if not payload:
            continue
        st[0] = (seq + len(payload)) & 0xFFFFFFFF
        ts = sec + usec / 1e6
        if st[1]:
            payload = st[1] + payload
            st[1] = b""
        p, size = 0, len(payload)
        is_request = st[2]
        while size - p >= 8:
            end = p + 6 + ((payload[p + 4] << 8) | payload[p + 5])
            if end > size:
                break
            tid = (payload[p] << 8) | payload[p + 1]
            unit = payload[p + 6]
            pdu = payload[p + 7 : end]
            p = end
            adus += 1
            if stage < 3:
                continue
            if is_request:
                pending[(st[3], tid, unit)] = (index, ts, pdu)
                req = None
            else:
                req = pending.pop((st[3], tid, unit), None)
            if stage < 4:
                index += 1
                continue
            parts = parts_of.get((pdu, is_request, unit))  # unbounded: a floor's best case
            if parts is None:
                parts = parts_of[(pdu, is_request, unit)] = _parts(
                    decode_pdu(pdu, not is_request), unit
                )
            to_line, hex_text, note = parts
            if clock[0] != sec:
                clock[0] = sec
                clock[1] = time.strftime("%H:%M:%S.", time.localtime(sec)).encode()
            when = b"%b%06d" % (clock[1], usec)
            if req is not None:
                latency = ts - req[1]
                text = note + b" (%.1f ms)" % (latency * 1000)
                latency_json = dumps(round(latency * 1000, 3))
                request_index = b"%d" % req[0]
            else:
                text, latency_json, request_index = note, b"null", b"null"
            line = b"%b  %b  [u%d t%d]  %b  | %b" % (when, st[5], unit, tid, hex_text, text)
            if stage == 5:
                lines.append(line)
            else:
                lines.append(
                    b'{"index":%d,"time":%b%b%d%b"%b","notes":["%b"],"crc_ok":null,'
                    b'"latency_ms":%b,"malformed":null,"request_index":%b}'
                    % (
                        index,
                        dumps(ts),
                        st[4],
                        tid,
                        to_line,
                        line,
                        note,
                        latency_json,
                        request_index,
                    )
                )
            index += 1
            if len(lines) >= 512:
                lines.append(b"")
                write(b"\n".join(lines))
                lines.clear()
        if p < size:
            st[1] = payload[p:]
    if lines:
        lines.append(b"")
        write(b"\n".join(lines))
    sys.stdout.flush()
    return adus


def _parts(pdu: object, unit: int) -> tuple[bytes, bytes, bytes]:
    """The fixed JSON parts of one PDU from one unit: from "unit" to "line":, hex, note."""
    import orjson

    from mbmon.format import generic_note, monitor_hex

    raw = pdu.raw  # type: ignore[attr-defined]
    values = pdu.values  # type: ignore[attr-defined]
    obj = {
        "unit": unit,
        "fc": pdu.fc,  # type: ignore[attr-defined]
        "kind": pdu.kind.value,  # type: ignore[attr-defined]
        "exception_code": pdu.exception_code,  # type: ignore[attr-defined]
        "address": pdu.address,  # type: ignore[attr-defined]
        "count": pdu.count,  # type: ignore[attr-defined]
        "values": list(values) if values is not None else None,
        "pdu": monitor_hex(raw),
    }
    to_line = b"," + orjson.dumps(obj)[1:-1] + b',"line":'
    note = orjson.dumps(generic_note(pdu))[1:-1]  # type: ignore[arg-type]
    return to_line, monitor_hex(raw).encode(), note


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--adus", type=int, default=1_000_000, help="ADUs in the capture (even)")
    ap.add_argument("--skip-tshark", action="store_true", help="leave tshark out")
    ap.add_argument(
        "--realistic",
        action="store_true",
        help="the realistic polling capture (bench/realistic.py), 8 connections",
    )
    ap.add_argument("--stage", type=int, choices=range(1, 6), help=argparse.SUPPRESS)
    ap.add_argument("--file", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.stage:  # a child: one floor stage
        adus = floor(args.file, args.stage)
        print(f"{adus} ADUs framed", file=sys.stderr)
        return 0

    n = args.adus
    if args.realistic:
        import realistic

        path = realistic.capture("polling", n, 8, 2, "aligned")
        stats = {"bytes": path.stat().st_size}
    else:
        path, stats = capture(n)
    load = os.getloadavg()
    print(
        f"capture: {path.relative_to(REPO)} ({stats['bytes']:,} bytes, {n:,} ADUs); "
        f"{os.cpu_count()} CPUs, load average {load[0]:.2f}; python {sys.version.split()[0]}"
    )
    runs: list[Run] = []
    for number, name in enumerate(STAGES, 1):
        cmd = [sys.executable, __file__, "--stage", str(number), "--file", str(path)]
        runs.append(measure(f"floor {number}: {name}", cmd, None))
    runs.append(measure("mbmon read --json", [*mbmon_cmd(), "read", str(path), "--json"], None))
    runs.append(measure("mbmon read (text)", [*mbmon_cmd(), "read", str(path)], None))
    tshark = None
    if not args.skip_tshark:
        tshark = measure("tshark -T fields", tshark_cmd(path), None)
        runs.append(tshark)
    print("results (stdout to /dev/null):")
    for run in runs:
        show(run, n)
    if any(run.rc for run in runs):
        print("  !! a run failed (see above); no verdict")
        return 1
    if tshark is not None:
        print("ratios to tshark's ADUs/s (the realistic target for read and read --json: >= 2.5):")
        for run in runs[:-1]:
            print(f"  {run.name:<26} {tshark.wall / run.wall:6.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
