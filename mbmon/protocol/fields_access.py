"""Field decoders of the data-access functions: bits and registers.

Reads (01-04), single writes (05, 06), multiple writes (0F, 10), mask write
(16), read/write multiple (17) and the FIFO queue (18). ``BY_SHAPE`` maps a
function-code table ``shape`` (and whether it addresses bits) to its request
and response decoders, so that a registered code of a known shape is decoded
like the public ones. Quantity limits come from the one table
(:data:`mbmon.protocol.lengths.MAX_COUNT`). Pure.
"""

from __future__ import annotations

import struct
from typing import Final

from mbmon.model import Pdu
from mbmon.protocol.fields import Decoder, Out, paired_request, u16, unpack_bits, unpack_words
from mbmon.protocol.functions import FUNCTIONS
from mbmon.protocol.lengths import MAX_COUNT

__all__ = ["BY_SHAPE", "FIFO"]


def _read_req(o: Out, request: Pdu | None) -> None:
    d = o.d
    if len(d) == 5:  # the usual case, decided without the helpers (same result)
        address = (d[1] << 8) | d[2]
        count = (d[3] << 8) | d[4]
        o.address = address
        o.count = count
        if not 1 <= count <= MAX_COUNT[o.fc]:
            o.limit("count", count, MAX_COUNT[o.fc])
        if address + count > 0x10000:
            o.span(address, count)
        return
    o.fixed(5)
    o.address, o.count = u16(d, 1), u16(d, 3)
    o.limit("count", o.count, MAX_COUNT[o.fc])
    o.span(o.address, o.count)


def _bits_resp(o: Out, request: Pdu | None) -> None:
    if not o.need(2):
        return
    data = o.counted(1)
    bits = unpack_bits(data)
    req = paired_request(request, o.fc)
    n = req.count if req is not None else None
    if n is not None:
        want = (n + 7) // 8
        if o.byte_count != want:
            o.bad.append(f"byte count {o.byte_count} but {n} bits need {want}")
        if len(bits) >= n:
            bits = bits[:n]
    elif o.byte_count == 0:
        o.bad.append("byte count 0")
    o.values = bits


def _regs_resp(o: Out, request: Pdu | None) -> None:
    d = o.d
    if len(d) < 2:
        o.need(2)
        return
    bc = d[1]
    if request is None and bc and not bc & 1 and len(d) == bc + 2:
        # the usual unpaired answer, decided without the helpers (same result)
        o.byte_count = bc
        o.values = struct.unpack_from(f">{bc >> 1}H", d, 2)
        return
    data = o.counted(1)
    bc = o.byte_count or 0
    if bc % 2:
        o.bad.append(f"odd byte count {bc}")
    req = paired_request(request, o.fc)
    n = req.count if req is not None else None
    if n is not None:
        if bc != 2 * n:
            o.bad.append(f"byte count {bc} but {n} registers need {2 * n}")
    elif bc == 0:
        o.bad.append("byte count 0")
    o.values = unpack_words(data)


def _write_coil(o: Out, request: Pdu | None) -> None:
    o.fixed(5)
    o.address = u16(o.d, 1)
    raw = u16(o.d, 3)
    o.count = 1
    if raw == 0xFF00:
        o.values = (1,)
    elif raw == 0x0000:
        o.values = (0,)
    elif raw is not None:
        o.fields["raw_value"] = raw
        o.bad.append(f"coil value 0x{raw:04X} is not 0xFF00/0x0000")


def _write_reg(o: Out, request: Pdu | None) -> None:
    o.fixed(5)
    o.address = u16(o.d, 1)
    v = u16(o.d, 3)
    o.count = 1
    if v is not None:
        o.values = (v,)


def _write_multi_req(o: Out, request: Pdu | None) -> None:
    d = o.d
    coils = FUNCTIONS[o.fc].bits
    o.address, o.count = u16(d, 1), u16(d, 3)
    if not o.need(6):
        return
    data = o.counted(5)
    bc = o.byte_count or 0
    n = o.count or 0
    o.limit("count", o.count, MAX_COUNT[o.fc])
    o.span(o.address, o.count)
    if coils:
        want = (n + 7) // 8
        bits = unpack_bits(data)
        if bc != want:
            o.bad.append(f"byte count {bc} but {n} bits need {want}")
        o.values = bits[:n] if len(bits) >= n else bits
    else:
        if bc != 2 * n:
            o.bad.append(f"byte count {bc} but {n} registers need {2 * n}")
        o.values = unpack_words(data)


def _write_multi_resp(o: Out, request: Pdu | None) -> None:
    o.fixed(5)
    o.address, o.count = u16(o.d, 1), u16(o.d, 3)
    o.limit("count", o.count, MAX_COUNT[o.fc])
    o.span(o.address, o.count)


def _mask_write(o: Out, request: Pdu | None) -> None:
    o.fixed(7)
    o.address = u16(o.d, 1)
    for name, i in (("and_mask", 3), ("or_mask", 5)):
        v = u16(o.d, i)
        if v is not None:
            o.fields[name] = v


def _rw_multi_req(o: Out, request: Pdu | None) -> None:
    d = o.d
    o.address, o.count = u16(d, 1), u16(d, 3)
    waddr, wcount = u16(d, 5), u16(d, 7)
    if waddr is not None:
        o.fields["write_address"] = waddr
    if wcount is not None:
        o.fields["write_count"] = wcount
    spec = FUNCTIONS[o.fc]
    o.limit("read count", o.count, spec.max_count or 0)
    o.limit("write count", wcount, spec.max_write_count or 0)
    o.span(o.address, o.count)
    o.span(waddr, wcount)
    if not o.need(10):
        return
    data = o.counted(9)
    o.byte_count = None  # the only byte count of a 0x17 request is the write part's
    wbc = d[9]
    o.fields["write_byte_count"] = wbc
    n = wcount or 0
    if wbc != 2 * n:
        o.bad.append(f"write byte count {wbc} but {n} registers need {2 * n}")
    o.fields["write_values"] = unpack_words(data)


def _fifo_req(o: Out, request: Pdu | None) -> None:
    o.fixed(3)
    o.address = u16(o.d, 1)


def _fifo_resp(o: Out, request: Pdu | None) -> None:
    if not o.need(3):
        return
    data = o.counted(1, width=2)
    bc = o.byte_count or 0
    fifo = u16(data, 0)
    if fifo is None:
        o.bad.append("no fifo count")
        return
    o.fields["fifo_count"] = fifo
    if fifo > 31:
        o.bad.append(f"fifo count {fifo} exceeds 31")
    if bc != 2 + 2 * fifo:
        o.bad.append(f"byte count {bc} but fifo count {fifo} needs {2 + 2 * fifo}")
    o.values = unpack_words(data[2:])


#: Field decoders of a table ``shape``: (shape, bits) -> (request, response decoder).
BY_SHAPE: Final[dict[tuple[str, bool], tuple[Decoder, Decoder]]] = {
    ("read", True): (_read_req, _bits_resp),
    ("read", False): (_read_req, _regs_resp),
    ("write_single", True): (_write_coil, _write_coil),
    ("write_single", False): (_write_reg, _write_reg),
    ("write_multiple", True): (_write_multi_req, _write_multi_resp),
    ("write_multiple", False): (_write_multi_req, _write_multi_resp),
    ("mask_write", False): (_mask_write, _mask_write),
    ("read_write", False): (_rw_multi_req, _regs_resp),
}
#: The FIFO queue's decoders (0x18 has no table shape: its layout is its own).
FIFO: Final[tuple[Decoder, Decoder]] = (_fifo_req, _fifo_resp)
