"""The fields of one frame, each with the bytes it describes: ``mbmon decode``'s lines
and the monitor's details pane share this one text (:func:`frame_details`)."""

from __future__ import annotations

from typing import Any

from mbmon.format import generic_note, monitor_hex
from mbmon.model import Frame, Kind, Pdu, Transport
from mbmon.protocol.functions import SHAPE

__all__ = ["Detail", "frame_details", "frame_text"]


#: Where a PDU's fields sit after the function code, per shape of the function-code
#: table (:data:`~mbmon.protocol.functions.SHAPE`) and kind: field -> (start, end)
#: offsets in the PDU (``None`` end: to the PDU's end).
_FIELD_AT: dict[tuple[str, Kind], dict[str, tuple[int, int | None]]] = {
    ("read", Kind.REQUEST): {"address": (1, 3), "count": (3, 5)},
    ("read", Kind.RESPONSE): {"byte_count": (1, 2), "values": (2, None)},
    ("write_single", Kind.REQUEST): {"address": (1, 3), "values": (3, 5)},
    ("write_single", Kind.RESPONSE): {"address": (1, 3), "values": (3, 5)},
    ("write_multiple", Kind.REQUEST): {
        "address": (1, 3),
        "count": (3, 5),
        "byte_count": (5, 6),
        "values": (6, None),
    },
    ("write_multiple", Kind.RESPONSE): {"address": (1, 3), "count": (3, 5)},
}

#: One line of a frame's details and the bytes of the ADU it describes (``None``: none).
Detail = tuple[str, tuple[int, int] | None]


def _detail_value(value: Any) -> str:
    """A field's value as the user typed bytes: hex for bytes, numbers comma-separated."""
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).hex(" ").upper()
    if isinstance(value, (tuple, list)):
        return ", ".join(_detail_value(v) for v in value)
    if isinstance(value, dict):
        return ", ".join(f"{k}: {_detail_value(v)}" for k, v in value.items())
    return str(value)


def frame_details(
    frame: Frame,
    notes: tuple[str, ...] | list[str] = (),
    *,
    framing: str | None = None,
    crc: str | None = None,
    request: Pdu | None = None,
) -> list[Detail]:
    """Every field of one frame as ``mbmon decode`` prints it (``unit: 1``, ``address: 200``,
    ..., ``note: ...``), each with the ``(start, end)`` bytes of ``frame.raw`` it describes.

    ``framing`` names the framing (``RTU ADU``, ``Modbus/TCP ADU``, ``PDU``; default:
    the stream's transport); ``crc`` the CRC's verdict (default: from ``crc_ok``);
    ``request`` the paired request of a response (its meaning then names the addresses
    read). The one text of a frame's fields, shared by ``decode`` and the monitor.
    """
    pdu, raw = frame.pdu, frame.raw
    rtu = frame.stream.transport is Transport.RTU
    at = 1 if rtu else len(raw) - len(pdu.raw)  # where the PDU starts in the ADU
    end = at + len(pdu.raw)
    if framing is None:
        framing = "RTU ADU" if rtu else ("Modbus/TCP ADU" if at else "PDU")
    out: list[Detail] = [(f"framing: {framing}", None)]
    if rtu or at:
        out.append((f"unit: {frame.unit}", (0, 1) if rtu else (6, 7)))
    if frame.tid is not None and at >= 7:
        out.append((f"transaction id: {frame.tid}", (0, 2)))
    if frame.crc_ok is not None:
        verdict = crc if crc is not None else ("ok" if frame.crc_ok else _bad_crc(raw, rtu))
        out.append((f"CRC: {verdict}", (len(raw) - 2, len(raw)) if rtu else None))
    out.append((f"kind: {pdu.kind.value}", (at, at + 1)))
    out.append((f"meaning: {generic_note(pdu, request)}", (at, end)))
    where = _FIELD_AT.get((SHAPE.get(pdu.fc, ""), pdu.kind), {})
    if pdu.kind is Kind.EXCEPTION:
        where = {"exception_code": (1, 2)}

    def span(name: str) -> tuple[int, int] | None:
        found = where.get(name)
        if found is None:
            return (at + 1, end) if len(pdu.raw) > 1 else None
        lo, hi = found
        return (at + lo, min(end, at + hi) if hi is not None else end)

    for name in ("address", "count", "byte_count", "exception_code"):
        value = getattr(pdu, name)
        if value is not None:
            out.append((f"{name.replace('_', ' ')}: {value}", span(name)))
    if pdu.values is not None:
        out.append(("values: " + ", ".join(str(v) for v in pdu.values), span("values")))
    for name, value in pdu.fields.items():
        out.append((f"{name.replace('_', ' ')}: {_detail_value(value)}", span(name)))
    if pdu.malformed:
        out.append((f"malformed: {pdu.malformed}", (at, end)))
    out.extend((f"note: {n}", None) for n in notes)
    return out


def _bad_crc(raw: bytes, rtu: bool) -> str:
    """The verdict on a CRC that failed: the CRC the RTU frame has, and the one it should."""
    if not rtu or len(raw) < 4:
        return "BAD"
    from mbmon.protocol.crc import crc_bytes

    expected = monitor_hex(crc_bytes(raw[:-2]))
    return f"BAD (the frame has {monitor_hex(raw[-2:])}, expected {expected})"


def frame_text(
    frame: Frame,
    notes: tuple[str, ...] | list[str] = (),
    *,
    framing: str | None = None,
    request: Pdu | None = None,
) -> list[str]:
    """``mbmon decode``'s lines for one frame: its PDU as the robot's Modbus Monitor
    shows it (:func:`monitor_hex`), then each field of :func:`frame_details`, indented."""
    details = frame_details(frame, notes, framing=framing, request=request)
    return [monitor_hex(frame.pdu.raw), *("  " + text for text, _span in details)]
