"""``mbmon decode``: one Modbus frame typed by hand (hex), decoded and explained."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from mbmon.commands.common import EXIT_OK, UsageError, make_annotator

EPILOG = """\
examples:
  mbmon decode 02 01 2C 00 05                 a PDU as the manual prints it (query)
  mbmon decode --response 02 01 13            the same PDU read as a response
  mbmon decode 01 03 00 00 00 0A C5 CD        an RTU ADU (recognised by its CRC)
  mbmon decode 00 01 00 00 00 06 01 03 00 00 00 01   a Modbus/TCP ADU (MBAP header)
  mbmon decode --profile hrss 10 00 C9 00 03 06 00 03 00 00 00 01
      the manual's Example 5 (JOG A1 +: R201 = 3, R202 = 0, R203 = 1) with HRSS meaning
"""


def register(sub: Any) -> None:
    """Add ``decode`` to the CLI's sub-parsers."""
    decode = sub.add_parser(
        "decode",
        help="decode one frame typed by hand (hex)",
        description="Decode one Modbus frame given as hex bytes, as the manual prints them. "
        "Without --rtu/--tcp/--pdu the framing is guessed: a valid CRC means RTU, a "
        "consistent MBAP header means TCP, anything else is a bare PDU.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    decode.add_argument("hex", nargs="+", metavar="HEX", help="bytes, e.g. 02 01 2C 00 05")
    mode = decode.add_mutually_exclusive_group()
    mode.add_argument("--rtu", dest="mode", action="store_const", const="rtu", help="RTU ADU")
    mode.add_argument("--tcp", dest="mode", action="store_const", const="tcp", help="MBAP ADU")
    mode.add_argument("--pdu", dest="mode", action="store_const", const="pdu", help="bare PDU")
    decode.add_argument(
        "--response", action="store_true", help="read the PDU as a response (default: request)"
    )
    decode.add_argument("--json", action="store_true", help="print the decoded fields as JSON")
    decode.add_argument(
        "--profile", action="append", default=[], metavar="SPEC", help="annotate with a profile"
    )
    decode.set_defaults(func=run)


def _parse_hex(words: list[str]) -> bytes:
    """The bytes typed: hex tokens, ``0x`` prefixes, commas and colons allowed; a lone
    digit among several tokens is one byte (``1 3 0 0`` is ``01 03 00 00``)."""
    text = " ".join(words).replace(",", " ").replace(":", " ")
    tokens = [t[2:] if t.lower().startswith("0x") else t for t in text.split()]
    for token in tokens:
        if len(token) % 2 and (len(token) > 1 or len(tokens) == 1):
            raise UsageError(
                f"odd number of hex digits in {token!r}: bytes are two digits each (e.g. 0A, not A)"
            )
    joined = "".join(t.zfill(2) for t in tokens)
    try:
        data = bytes.fromhex(joined)
    except ValueError:
        raise UsageError(f"not hex bytes: {' '.join(words)!r}") from None
    if not data:
        raise UsageError("no bytes given")
    return data


def run(args: argparse.Namespace) -> int:
    """``mbmon decode``: one frame typed by hand, its fields and meaning."""
    from mbmon.format import View, frame_details, monitor_hex, record_to_json
    from mbmon.model import (
        Direction,
        Frame,
        Kind,
        Record,
        RecordKind,
        Stream,
        Transaction,
        Transport,
        TxStatus,
    )
    from mbmon.protocol.crc import check_crc, crc_bytes
    from mbmon.protocol.pdu import decode_pdu

    data = _parse_hex(args.hex)
    mode = args.mode
    guessed_bad_crc = False
    if mode is None:
        if len(data) >= 4 and check_crc(data):
            mode = "rtu"
        elif len(data) >= 8 and data[2:4] == b"\0\0" and int.from_bytes(data[4:6]) == len(data) - 6:
            mode = "tcp"
        elif _rtu_with_bad_crc(data, args.response):
            mode, guessed_bad_crc = "rtu", True
        else:
            mode = "pdu"
    unit: int | None = None
    tid: int | None = None
    crc_ok: bool | None = None
    crc_note = "ok"
    if mode == "rtu":
        if len(data) < 4:
            raise UsageError("an RTU ADU needs at least 4 bytes (unit, function code, CRC)")
        unit, body, crc_ok = data[0], data[1:-2], check_crc(data)
        if not crc_ok:
            expected = crc_bytes(data[:-2]).hex(" ").upper()
            crc_note = f"BAD (the frame has {data[-2:].hex(' ').upper()}, expected {expected})"
    elif mode == "tcp":
        if len(data) < 8:
            raise UsageError("a Modbus/TCP ADU needs at least 8 bytes (7-byte MBAP header + fc)")
        tid, unit, body = int.from_bytes(data[0:2]), data[6], data[7:]
        length = int.from_bytes(data[4:6])
        if length != len(data) - 6:
            print(
                f"mbmon: warning: MBAP length field says {length}, {len(data) - 6} bytes follow",
                file=sys.stderr,
            )
    else:
        body = data
    response = args.response or bool(body and body[0] & 0x80)
    pdu = decode_pdu(body, response)
    transport = {"rtu": Transport.RTU, "tcp": Transport.TCP}.get(mode, Transport.TCP)
    stream = Stream(0, transport, "client", "server")
    direction = Direction.S2C if response else Direction.C2S
    frame = Frame(0.0, stream, direction, unit if unit is not None else 0, tid, pdu, data, crc_ok)
    notes: tuple[str, ...] = ()
    annotator = make_annotator(args.profile)
    if annotator is not None:
        if response:
            tx = Transaction(0.0, TxStatus.UNSOLICITED, None, frame)
        else:
            tx = Transaction(0.0, TxStatus.PENDING, frame, None)
        notes = annotator.annotate(tx).notes
    kind = {Kind.REQUEST: RecordKind.REQUEST, Kind.RESPONSE: RecordKind.RESPONSE}.get(
        pdu.kind, RecordKind.EXCEPTION
    )
    record = Record(0, 0.0, kind, stream, frame=frame, notes=notes)
    if args.json:
        obj = record_to_json(record, View())
        obj["framing"] = mode
        if guessed_bad_crc:
            obj["framing_note"] = "guessed: an RTU frame with a bad CRC"
        if mode == "pdu":
            obj["transport"] = "pdu"
            obj["unit"] = None
        for key in ("index", "time", "stream", "src", "dst", "line", "request_index"):
            obj.pop(key, None)
        print(json.dumps(obj, ensure_ascii=False))
        return EXIT_OK
    print(monitor_hex(pdu.raw))
    framing = {"rtu": "RTU ADU", "tcp": "Modbus/TCP ADU", "pdu": "PDU"}[mode]
    if guessed_bad_crc:
        framing += (
            " with a bad CRC (guessed: unit, function code and length make an RTU frame, "
            "but the CRC does not match; --pdu reads the bytes as a bare PDU)"
        )
    details = frame_details(frame, notes, framing=framing, crc=crc_note)
    print("\n".join("  " + text for text, _span in details))
    return EXIT_OK


def _rtu_with_bad_crc(data: bytes, response: bool) -> bool:
    """Whether bytes whose CRC fails still look like an RTU ADU rather than a PDU: a
    unit id 0..247, a known function code whose PDU, read between the unit and the
    last two bytes, is well formed and exactly that long, while the same bytes read
    as a bare PDU are not well formed (``01 03 00 00 00 0A C5 CE``)."""
    from mbmon.protocol.functions import FUNCTIONS
    from mbmon.protocol.pdu import decode_pdu, pdu_length

    if len(data) < 4 or data[0] > 247 or (data[1] & 0x7F) not in FUNCTIONS:
        return False
    body = data[1:-2]
    as_response = response or bool(body[0] & 0x80)
    if pdu_length(body, as_response) != len(body) or decode_pdu(body, as_response).malformed:
        return False
    return bool(decode_pdu(data, response or bool(data[0] & 0x80)).malformed)

