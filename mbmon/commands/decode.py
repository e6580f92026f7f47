"""``mbmon decode``: one Modbus frame typed by hand (hex), decoded and explained."""

from __future__ import annotations

import argparse
import json
from typing import Any

from mbmon.commands.common import UsageError, attach_outputs, err, exit_status, make_annotator

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
    """``mbmon decode``: options → the typed bytes as a source
    (:class:`~mbmon.sources.typed.TypedFrameSource`) and the printer of its records
    → ``run_sources`` → the exit status. What is printed is what the one flow made
    of the bytes, in :mod:`mbmon.format`'s words (:func:`~mbmon.details.frame_text`,
    or the one JSON record of :func:`~mbmon.format.record_to_json` with the framing)."""
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline
    from mbmon.sources.base import run_sources
    from mbmon.sources.typed import TypedFrameError, TypedFrameSource

    data = _parse_hex(args.hex)
    mode, guessed_bad_crc = _framing(data, args.mode, args.response)
    try:
        source = TypedFrameSource(data, mode, response=args.response)  # type: ignore[arg-type]
    except TypedFrameError as exc:
        raise UsageError(str(exc)) from None
    length = int.from_bytes(data[4:6])
    if mode == "tcp" and length != len(data) - 6:
        err(f"warning: MBAP length field says {length}, {len(data) - 6} bytes follow")
    hub = Hub(Pipeline(make_annotator(args.profile)))
    source.open(hub)
    attach_outputs(hub, screen=_Printer(mode, guessed_bad_crc, as_json=args.json))
    try:
        run_sources(hub, [source])
    finally:
        hub.close()
    return exit_status(hub)


#: how ``decode`` names each framing (``framing:`` line)
_FRAMINGS = {"rtu": "RTU ADU", "tcp": "Modbus/TCP ADU", "pdu": "PDU"}


class _Printer:
    """``decode``'s screen: each frame record of the run as :func:`~mbmon.details.frame_text`
    gives it (``--json``: :func:`_json`); records without a frame (a command the
    profile's session saw written) are not shown."""

    def __init__(self, mode: str, guessed_bad_crc: bool, *, as_json: bool) -> None:
        self.mode = mode
        self.guessed = guessed_bad_crc
        self.as_json = as_json

    def on_record(self, record: Any) -> None:
        from mbmon.details import frame_text

        if record.frame is None:
            return
        if self.as_json:
            print(json.dumps(_json(record, self.mode, self.guessed), ensure_ascii=False))
            return
        framing = _FRAMINGS[self.mode]
        if self.guessed:
            framing += (
                " with a bad CRC (guessed: unit, function code and length make an RTU frame, "
                "but the CRC does not match; --pdu reads the bytes as a bare PDU)"
            )
        print("\n".join(frame_text(record.frame, record.notes, framing=framing)))


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


def _json(record: Any, mode: str, guessed: bool) -> dict[str, Any]:
    """The one JSON record of the frame, with its framing and without what a frame typed
    alone has not (index, time, stream, endpoints, line)."""
    from mbmon.format import View, record_to_json

    obj = record_to_json(record, View())
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
