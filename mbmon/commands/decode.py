"""``mbmon decode``: one Modbus frame typed by hand (hex), decoded and explained."""

from __future__ import annotations

import argparse
import json
from typing import Any

from mbmon.commands.common import UsageError, err, exit_status, make_annotator

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
    """``mbmon decode``: one frame typed by hand, its fields and meaning, in
    :mod:`mbmon.format`'s words (:func:`~mbmon.details.frame_text`, or the one JSON
    record of :func:`~mbmon.format.record_to_json` with the framing added)."""
    from mbmon.details import frame_text

    data = _parse_hex(args.hex)
    mode, guessed_bad_crc = _framing(data, args.mode, args.response)
    frame = _frame(data, mode, args.response)
    notes = _notes(frame, make_annotator(args.profile))
    if args.json:
        print(json.dumps(_json(frame, notes, mode, guessed_bad_crc), ensure_ascii=False))
        return exit_status()
    framing = _FRAMINGS[mode]
    if guessed_bad_crc:
        framing += (
            " with a bad CRC (guessed: unit, function code and length make an RTU frame, "
            "but the CRC does not match; --pdu reads the bytes as a bare PDU)"
        )
    print("\n".join(frame_text(frame, notes, framing=framing)))
    return exit_status()


#: how ``decode`` names each framing (``framing:`` line)
_FRAMINGS = {"rtu": "RTU ADU", "tcp": "Modbus/TCP ADU", "pdu": "PDU"}


def _framing(data: bytes, mode: str | None, response: bool) -> tuple[str, bool]:
    """``rtu``, ``tcp`` or ``pdu`` (``mode`` when given, else guessed: a valid CRC means
    RTU, a consistent MBAP header TCP, bytes that frame as RTU but for their CRC RTU
    too), and whether the guess is an RTU frame with a bad CRC."""
    from mbmon.protocol.crc import check_crc

    if mode is not None:
        return mode, False
    if len(data) >= 4 and check_crc(data):
        return "rtu", False
    if len(data) >= 8 and data[2:4] == b"\0\0" and int.from_bytes(data[4:6]) == len(data) - 6:
        return "tcp", False
    if _rtu_with_bad_crc(data, response):
        return "rtu", True
    return "pdu", False


def _frame(data: bytes, mode: str, response: bool) -> Any:
    """The :class:`~mbmon.model.Frame` of the typed bytes in ``mode``'s framing (unit,
    transaction id, CRC verdict); too few bytes for the framing is a usage error."""
    from mbmon.model import Direction, Frame, Stream, Transport
    from mbmon.protocol.crc import check_crc
    from mbmon.protocol.pdu import decode_pdu

    unit: int | None = None
    tid: int | None = None
    crc_ok: bool | None = None
    body = data
    if mode == "rtu":
        if len(data) < 4:
            raise UsageError("an RTU ADU needs at least 4 bytes (unit, function code, CRC)")
        unit, body, crc_ok = data[0], data[1:-2], check_crc(data)
    elif mode == "tcp":
        if len(data) < 8:
            raise UsageError("a Modbus/TCP ADU needs at least 8 bytes (7-byte MBAP header + fc)")
        tid, unit, body = int.from_bytes(data[0:2]), data[6], data[7:]
        length = int.from_bytes(data[4:6])
        if length != len(data) - 6:
            err(f"warning: MBAP length field says {length}, {len(data) - 6} bytes follow")
    response = response or bool(body and body[0] & 0x80)
    transport = Transport.RTU if mode == "rtu" else Transport.TCP
    stream = Stream(0, transport, "client", "server")
    direction = Direction.S2C if response else Direction.C2S
    pdu = decode_pdu(body, response)
    return Frame(0.0, stream, direction, unit if unit is not None else 0, tid, pdu, data, crc_ok)


def _notes(frame: Any, annotator: Any) -> tuple[str, ...]:
    """The profiles' notes on the frame, read alone (a request pending, or an answer
    nothing asked for)."""
    if annotator is None:
        return ()
    from mbmon.model import Direction, Transaction, TxStatus

    if frame.direction is Direction.S2C:
        tx = Transaction(0.0, TxStatus.UNSOLICITED, None, frame)
    else:
        tx = Transaction(0.0, TxStatus.PENDING, frame, None)
    notes: tuple[str, ...] = annotator.annotate(tx).notes
    return notes


def _json(frame: Any, notes: tuple[str, ...], mode: str, guessed: bool) -> dict[str, Any]:
    """The one JSON record of the frame, with its framing and without what a frame typed
    alone has not (index, time, stream, endpoints, line)."""
    from mbmon.format import View, record_to_json
    from mbmon.model import Kind, Record, RecordKind

    kinds = {Kind.REQUEST: RecordKind.REQUEST, Kind.RESPONSE: RecordKind.RESPONSE}
    kind = kinds.get(frame.pdu.kind, RecordKind.EXCEPTION)
    obj = record_to_json(Record(0, 0.0, kind, frame.stream, frame=frame, notes=notes), View())
    obj["framing"] = mode
    if guessed:
        obj["framing_note"] = "guessed: an RTU frame with a bad CRC"
    if mode == "pdu":
        obj["transport"] = "pdu"
        obj["unit"] = None
    for key in ("index", "time", "stream", "src", "dst", "line", "request_index"):
        obj.pop(key, None)
    return obj


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
